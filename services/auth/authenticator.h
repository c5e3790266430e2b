// Authentication: from what a caller presents (a bearer token, the common
// name of a verified client certificate) to a Principal, against the
// credentials file (credentials.proto). Transport-neutral: the gRPC layer
// and the HTTP layer both extract PresentedCredentials and call Authenticate.
#ifndef FLEETMEM_SERVICES_AUTH_AUTHENTICATOR_H_
#define FLEETMEM_SERVICES_AUTH_AUTHENTICATOR_H_

#include <cstddef>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "services/auth/access_policy.h"

namespace fleetmem::auth {

// One principal of the credentials file with how it proves who it is.
struct CredentialEntry {
  Principal principal;
  std::string secret_hash;              // Argon2id string; empty: no token
  std::string certificate_common_name;  // empty: no certificate
};

// Parses and validates the text of a credentials file. INVALID_ARGUMENT
// naming line and column for a syntax error, or the principal and field for
// a bad value: invalid or repeated name, no role, a robot without a valid
// robot id, a bad fleet id, neither secret_hash nor certificate, a malformed
// secret hash, a certificate name used twice.
absl::StatusOr<std::vector<CredentialEntry>> ParseCredentials(
    absl::string_view text);

// The token a client sends: "NAME:SECRET" (as `authorization: Bearer
// NAME:SECRET`). The name is the principal's; the secret has no ':'.
std::string MakeToken(absl::string_view name, absl::string_view secret);

// The token of an Authorization header value "Bearer NAME:SECRET"; a value
// without the "Bearer " prefix is returned whole (it then fails the check).
// Shared by the gRPC and HTTP transports.
std::string TokenFromAuthorization(absl::string_view value);

struct PresentedCredentials {
  // The bearer token, if the caller sent one.
  std::optional<std::string> token;
  // The common name of a client certificate the TLS layer has verified.
  std::optional<std::string> certificate_common_name;
};

// Thread-safe. A token is checked with Argon2id (about 0.1 s) the first time
// it is seen after a (re)load; the outcome is then cached under a keyed
// BLAKE2b digest of the token (never the token itself), so later calls cost
// a hash lookup.
class Authenticator {
 public:
  explicit Authenticator(std::vector<CredentialEntry> entries);

  // Swaps in a new credentials set (SIGHUP) and forgets every cached check.
  void Replace(std::vector<CredentialEntry> entries);

  // The principal of a valid token (preferred when both are present) or of
  // the client certificate. UNAUTHENTICATED when neither is presented, or
  // for an unknown or wrong token or an unknown certificate name (the
  // message does not say which part was wrong).
  absl::StatusOr<Principal> Authenticate(
      const PresentedCredentials& presented) const;

  size_t size() const;

 private:
  struct Set;
  absl::StatusOr<Principal> CheckToken(const std::shared_ptr<const Set>& set,
                                       const std::string& token) const;
  std::shared_ptr<const Set> Current() const;

  mutable absl::Mutex mu_;
  // Each set carries its own cache of checked tokens, so a check that ran
  // against an older set can never be cached for a newer one.
  std::shared_ptr<const Set> set_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::auth

#endif  // FLEETMEM_SERVICES_AUTH_AUTHENTICATOR_H_
