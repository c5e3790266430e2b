#include "services/transport/peer_forwarder.h"

#include <algorithm>
#include <memory>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "grpcpp/create_channel.h"
#include "grpcpp/generic/generic_stub.h"
#include "grpcpp/impl/codegen/proto_utils.h"
#include "grpcpp/security/credentials.h"
#include "grpcpp/support/channel_arguments.h"
#include "services/core/absl_view.h"
#include "services/transport/fleet_memory.h"

namespace fleetmem::transport {

PeerForwarder::PeerForwarder(PeerOptions options)
    : options_(std::move(options)) {}

std::shared_ptr<grpc::Channel> PeerForwarder::ChannelTo(
    const std::string& address) {
  absl::MutexLock lock(&mu_);
  auto it = channels_.find(address);
  if (it != channels_.end()) return it->second;
  std::shared_ptr<grpc::ChannelCredentials> credentials;
  if (options_.ca_pem.empty()) {
    credentials = grpc::InsecureChannelCredentials();
  } else {
    grpc::SslCredentialsOptions ssl;
    ssl.pem_root_certs = options_.ca_pem;
    credentials = grpc::SslCredentials(ssl);
  }
  grpc::ChannelArguments arguments;
  if (!options_.tls_server_name.empty()) {
    arguments.SetSslTargetNameOverride(options_.tls_server_name);
  }
  std::shared_ptr<grpc::Channel> channel =
      grpc::CreateCustomChannel(address, credentials, arguments);
  channels_.emplace(address, channel);
  return channel;
}

absl::Status PeerForwarder::Forward(const std::string& address,
                                    std::string_view method,
                                    const google::protobuf::Message& request,
                                    google::protobuf::Message* response,
                                    absl::Time deadline) {
  const PeerCall call{address, response};
  return ForwardEach(std::span<const PeerCall>(&call, 1), method, request,
                     deadline)
      .front();
}

std::vector<absl::Status> PeerForwarder::ForwardEach(
    std::span<const PeerCall> calls, std::string_view method,
    const google::protobuf::Message& request, absl::Time deadline) {
  deadline = std::min(deadline, absl::Now() + options_.timeout);
  const std::string path =
      absl::StrCat("/fleetmem.v1.MemoryService/", V(method));
  // One context per call; the answers are counted down in a state the
  // callbacks share, so that none touches this frame after it returned.
  struct Answers {
    absl::Mutex mu;
    std::vector<grpc::Status> statuses ABSL_GUARDED_BY(mu);
    size_t pending ABSL_GUARDED_BY(mu) = 0;
  };
  auto answers = std::make_shared<Answers>();
  {
    absl::MutexLock lock(&answers->mu);
    answers->statuses.resize(calls.size());
    answers->pending = calls.size();
  }
  std::vector<grpc::ClientContext> contexts(calls.size());
  for (size_t i = 0; i < calls.size(); ++i) {
    grpc::ClientContext& context = contexts[i];
    context.set_deadline(absl::ToChronoTime(deadline));
    context.AddMetadata(kForwardedHeader, "1");
    if (!options_.token.empty()) {
      context.AddMetadata("authorization",
                          absl::StrCat("Bearer ", options_.token));
    }
    grpc::TemplatedGenericStub<google::protobuf::Message,
                               google::protobuf::Message>
        stub(ChannelTo(calls[i].address));
    stub.UnaryCall(&context, path, grpc::StubOptions(), &request,
                   calls[i].response, [answers, i](grpc::Status answered) {
                     absl::MutexLock lock(&answers->mu);
                     answers->statuses[i] = std::move(answered);
                     --answers->pending;
                   });
  }
  std::vector<grpc::Status> answered;
  {
    absl::MutexLock lock(&answers->mu);
    answers->mu.Await(absl::Condition(
        +[](size_t* left) { return *left == 0; }, &answers->pending));
    answered = answers->statuses;
  }
  std::vector<absl::Status> statuses;
  statuses.reserve(calls.size());
  for (size_t i = 0; i < calls.size(); ++i) {
    const grpc::Status& status = answered[i];
    const auto code = static_cast<absl::StatusCode>(status.error_code());
    if (status.ok()) {
      statuses.push_back(absl::OkStatus());
    } else if (code == absl::StatusCode::kUnavailable ||
               code == absl::StatusCode::kDeadlineExceeded) {
      statuses.emplace_back(code, absl::StrCat("replica ", calls[i].address,
                                               ": ", status.error_message()));
    } else {
      statuses.emplace_back(code, status.error_message());
    }
  }
  return statuses;
}

}  // namespace fleetmem::transport
