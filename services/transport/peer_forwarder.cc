#include "services/transport/peer_forwarder.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/notification.h"
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
                                    google::protobuf::Message* response) {
  grpc::TemplatedGenericStub<google::protobuf::Message,
                             google::protobuf::Message>
      stub(ChannelTo(address));
  grpc::ClientContext context;
  context.set_deadline(absl::ToChronoTime(absl::Now() + options_.timeout));
  context.AddMetadata(kForwardedHeader, "1");
  if (!options_.token.empty()) {
    context.AddMetadata("authorization",
                        absl::StrCat("Bearer ", options_.token));
  }
  absl::Notification done;
  grpc::Status status;
  stub.UnaryCall(
      &context, absl::StrCat("/fleetmem.v1.MemoryService/", V(method)),
      grpc::StubOptions(), &request, response, [&](grpc::Status answered) {
        status = std::move(answered);
        done.Notify();
      });
  done.WaitForNotification();
  if (status.ok()) return absl::OkStatus();
  const auto code = static_cast<absl::StatusCode>(status.error_code());
  if (code == absl::StatusCode::kUnavailable ||
      code == absl::StatusCode::kDeadlineExceeded) {
    return absl::Status(
        code, absl::StrCat("replica ", address, ": ", status.error_message()));
  }
  return absl::Status(code, status.error_message());
}

}  // namespace fleetmem::transport
