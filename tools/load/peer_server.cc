#include "tools/load/peer_server.h"

#include <grpcpp/grpcpp.h>

#include "absl/strings/str_cat.h"
#include "fleetmem/v1/memory.grpc.pb.h"

namespace fleetmem::load {
namespace {

class DiscardService final : public v1::MemoryService::Service {
 public:
  grpc::Status UploadTraces(grpc::ServerContext*,
                            grpc::ServerReader<v1::UploadTracesRequest>* reader,
                            v1::UploadTracesResponse* response) override {
    v1::UploadTracesRequest request;
    uint64_t traces = 0;
    while (reader->Read(&request)) traces += request.traces_size();
    response->set_accepted(traces);
    return grpc::Status::OK;
  }
  grpc::Status QueryPlace(grpc::ServerContext*, const v1::QueryPlaceRequest*,
                          v1::QueryPlaceResponse*) override {
    return grpc::Status::OK;
  }
  grpc::Status SampleReplay(grpc::ServerContext*,
                            const v1::SampleReplayRequest*,
                            v1::SampleReplayResponse*) override {
    return grpc::Status::OK;
  }
  grpc::Status GetStats(grpc::ServerContext*, const v1::GetStatsRequest*,
                        v1::GetStatsResponse*) override {
    return grpc::Status::OK;
  }
};

}  // namespace

struct PeerServer::Impl {
  DiscardService service;
  std::unique_ptr<grpc::Server> server;
};

absl::StatusOr<std::unique_ptr<PeerServer>> PeerServer::Start(
    const std::string& listen) {
  auto peer = std::unique_ptr<PeerServer>(new PeerServer());
  peer->impl_ = std::make_unique<Impl>();
  int port = 0;
  grpc::ServerBuilder builder;
  builder.AddListeningPort(listen, grpc::InsecureServerCredentials(), &port);
  builder.SetMaxReceiveMessageSize(64 << 20);
  builder.RegisterService(&peer->impl_->service);
  peer->impl_->server = builder.BuildAndStart();
  if (peer->impl_->server == nullptr || port == 0) {
    return absl::UnavailableError(
        absl::StrCat("peer server: cannot listen on ", listen));
  }
  peer->address_ = absl::StrCat(listen.substr(0, listen.rfind(':')), ":", port);
  return peer;
}

PeerServer::~PeerServer() { Shutdown(); }

void PeerServer::Wait() { impl_->server->Wait(); }

void PeerServer::Shutdown() {
  if (impl_ != nullptr && impl_->server != nullptr) impl_->server->Shutdown();
}

}  // namespace fleetmem::load
