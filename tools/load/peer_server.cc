#include "tools/load/peer_server.h"

#include <fcntl.h>
#include <grpcpp/grpcpp.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdint>
#include <cstring>
#include <mutex>
#include <string>

#include "absl/strings/str_cat.h"
#include "fleetmem/v1/memory.grpc.pb.h"

namespace fleetmem::load {
namespace {

class DiscardService final : public v1::MemoryService::Service {
 public:
  // `fd` >= 0: the durable peer's file (owned by the caller).
  explicit DiscardService(int fd) : fd_(fd) {}

  grpc::Status UploadTraces(grpc::ServerContext*,
                            grpc::ServerReader<v1::UploadTracesRequest>* reader,
                            v1::UploadTracesResponse* response) override {
    v1::UploadTracesRequest request;
    uint64_t traces = 0;
    std::string bytes;
    while (reader->Read(&request)) {
      if (fd_ >= 0) {
        request.SerializeToString(&bytes);
        if (grpc::Status synced = AppendSynced(bytes); !synced.ok()) {
          return synced;
        }
      }
      traces += request.traces_size();
      if (request.traces_size() > 0) {
        dimension_.store(request.traces(0).code_size());
      }
    }
    response->set_accepted(traces);
    return grpc::Status::OK;
  }
  // Answers carry as many traces of the asked dimension as the server's
  // would (k matches; `count` samples of the fleet's dimension, which the
  // peer learns from the uploads it discards), so both send the same bytes.
  grpc::Status QueryPlace(grpc::ServerContext*,
                          const v1::QueryPlaceRequest* request,
                          v1::QueryPlaceResponse* response) override {
    const v1::MemoryTrace trace = Filler(request->code_size());
    for (uint32_t i = 0; i < std::max<uint32_t>(1, request->k()); ++i) {
      v1::PlaceMatch* match = response->add_matches();
      *match->mutable_trace() = trace;
      match->set_distance(0.5f);
    }
    return grpc::Status::OK;
  }
  grpc::Status SampleReplay(grpc::ServerContext*,
                            const v1::SampleReplayRequest* request,
                            v1::SampleReplayResponse* response) override {
    const v1::MemoryTrace trace = Filler(dimension_.load());
    for (uint32_t i = 0; i < request->count(); ++i) {
      *response->add_traces() = trace;
    }
    return grpc::Status::OK;
  }
  grpc::Status GetStats(grpc::ServerContext*, const v1::GetStatsRequest*,
                        v1::GetStatsResponse*) override {
    return grpc::Status::OK;
  }

 private:
  // A trace of `dimension` as a server would return it.
  static v1::MemoryTrace Filler(int dimension) {
    v1::MemoryTrace trace;
    trace.set_robot_id("peer-robot-0");
    trace.set_seq(12345);
    trace.set_domain("peer");
    for (int i = 0; i < dimension; ++i) trace.add_code(0.0625f * (i % 7));
    trace.mutable_pose()->set_x(1.5);
    trace.mutable_pose()->set_y(-2.5);
    trace.set_reward(0.75f);
    trace.set_cluster_id(7);
    trace.set_replay_count(1);
    return trace;
  }

  // The durable peer's append: one message, then fdatasync, one at a time.
  grpc::Status AppendSynced(const std::string& bytes) {
    const std::lock_guard lock(file_mu_);
    for (size_t written = 0; written < bytes.size();) {
      const ssize_t n =
          ::write(fd_, bytes.data() + written, bytes.size() - written);
      if (n < 0 && errno == EINTR) continue;
      if (n < 0) {
        return grpc::Status(grpc::StatusCode::INTERNAL,
                            absl::StrCat("peer: write: ", strerror(errno)));
      }
      written += static_cast<size_t>(n);
    }
    if (::fdatasync(fd_) != 0) {
      return grpc::Status(grpc::StatusCode::INTERNAL,
                          absl::StrCat("peer: fdatasync: ", strerror(errno)));
    }
    return grpc::Status::OK;
  }

  const int fd_;
  std::mutex file_mu_;
  // Code dimension of the last upload seen (samples of 0-d traces before).
  std::atomic<int> dimension_{256};
};

}  // namespace

struct PeerServer::Impl {
  explicit Impl(int fd) : fd(fd), service(fd) {}
  ~Impl() {
    server.reset();  // shut down by ~PeerServer: no call writes to fd now
    if (fd >= 0) ::close(fd);
  }
  const int fd;
  DiscardService service;
  std::unique_ptr<grpc::Server> server;
};

absl::StatusOr<std::unique_ptr<PeerServer>> PeerServer::Start(
    const std::string& listen, PeerOptions options) {
  int fd = -1;
  if (!options.durable_file.empty()) {
    fd = ::open(options.durable_file.c_str(),
                O_WRONLY | O_CREAT | O_TRUNC | O_APPEND | O_CLOEXEC, 0644);
    if (fd < 0) {
      return absl::FailedPreconditionError(
          absl::StrCat("durable peer: cannot make ", options.durable_file, ": ",
                       strerror(errno)));
    }
  }
  auto peer = std::unique_ptr<PeerServer>(new PeerServer());
  peer->impl_ = std::make_unique<Impl>(fd);
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
