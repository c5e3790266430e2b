#include "services/transport/call_auth.h"

#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "grpc/grpc_security_constants.h"
#include "grpcpp/security/auth_context.h"

namespace fleetmem::transport {

auth::PresentedCredentials PresentedBy(
    const grpc::CallbackServerContext& context) {
  auth::PresentedCredentials presented;
  presented.peer = context.peer();
  const auto& metadata = context.client_metadata();
  if (auto it = metadata.find("authorization"); it != metadata.end()) {
    presented.token = auth::TokenFromAuthorization(
        absl::string_view(it->second.data(), it->second.size()));
  }
  const std::shared_ptr<const grpc::AuthContext> auth = context.auth_context();
  if (auth != nullptr && auth->IsPeerAuthenticated()) {
    const std::vector<grpc::string_ref> names =
        auth->FindPropertyValues(GRPC_X509_CN_PROPERTY_NAME);
    if (!names.empty()) {
      presented.certificate_common_name =
          std::string(names.front().data(), names.front().size());
    }
  }
  return presented;
}

std::string ClientName(const auth::Authenticator* authenticator,
                       const grpc::CallbackServerContext& context,
                       const auth::Principal& caller) {
  if (authenticator != nullptr) return "principal:" + caller.name;
  auth::PresentedCredentials presented = PresentedBy(context);
  if (presented.token.has_value()) {
    const size_t colon = presented.token->rfind(':');
    return "token:" + presented.token->substr(0, colon);
  }
  if (presented.certificate_common_name.has_value()) {
    return "certificate:" + *presented.certificate_common_name;
  }
  const std::string peer = context.peer();
  const size_t colon = peer.rfind(':');
  return colon == std::string::npos || colon < peer.find(':') + 1
             ? peer
             : peer.substr(0, colon);
}

absl::StatusOr<auth::Principal> AuthenticateCall(
    const auth::Authenticator* authenticator,
    const grpc::CallbackServerContext& context) {
  if (authenticator == nullptr) return auth::Principal::Anonymous();
  return authenticator->Authenticate(PresentedBy(context));
}

}  // namespace fleetmem::transport
