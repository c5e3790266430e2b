// The gRPC side of the access policy: what a call presents (the
// `authorization: Bearer NAME:SECRET` header, the common name of a client
// certificate verified by TLS) goes to auth::Authenticator, and the
// principal to auth::Authorize (by MemoryApi, after AuthenticateCall).
#ifndef FLEETMEM_SERVICES_TRANSPORT_CALL_AUTH_H_
#define FLEETMEM_SERVICES_TRANSPORT_CALL_AUTH_H_

#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "grpcpp/server_context.h"
#include "services/auth/access_policy.h"
#include "services/auth/authenticator.h"

namespace fleetmem::transport {

// What the caller of `context` presents.
auth::PresentedCredentials PresentedBy(
    const grpc::CallbackServerContext& context);

// Who a call comes from, for per-client limits. With auth on, the
// authenticated `caller`'s name ("principal:robot-7"): only a caller holding
// the secret can use that principal's slots. With auth off (`authenticator`
// null) nothing is verified: the name part of its token, else its
// certificate's common name, else its address without the port
// ("ipv4:10.0.0.7").
std::string ClientName(const auth::Authenticator* authenticator,
                       const grpc::CallbackServerContext& context,
                       const auth::Principal& caller);

// The caller's principal: auth::Principal::Anonymous() when `authenticator`
// is null (auth off), else Authenticate's (UNAUTHENTICATED on failure).
absl::StatusOr<auth::Principal> AuthenticateCall(
    const auth::Authenticator* authenticator,
    const grpc::CallbackServerContext& context);

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_CALL_AUTH_H_
