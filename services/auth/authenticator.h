// Authentication: from what a caller presents (a bearer token, the common
// name of a verified client certificate) to a Principal, against the
// credentials file (credentials.proto). Transport-neutral: the gRPC layer
// and the HTTP layer both extract PresentedCredentials and call Authenticate.
#ifndef FLEETMEM_SERVICES_AUTH_AUTHENTICATOR_H_
#define FLEETMEM_SERVICES_AUTH_AUTHENTICATOR_H_

#include <cstddef>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
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
// secret hash, a certificate name used twice, a robot id held by two robot
// principals that share a fleet.
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
  // The connection it came over, "ADDRESS:PORT" (gRPC's peer, e.g.
  // "ipv4:127.0.0.1:50212"): what costly checks are throttled by. Empty:
  // one unnamed connection.
  std::string peer;
};

// What failed token checks may cost. A token for a known name is checked
// with Argon2id (about 0.1 s of a core and 64 MiB) the first time it is seen;
// without a bound, wrong secrets for a robot's name would each cost that
// much, and a few clients could take the server's CPU and memory.
//
// Throttling falls on the connections that present wrong secrets, never on
// the principal whose name they carry (the third outside sweep: wrong
// secrets under robot-8's name kept robot-8's own valid token out, 120 of
// 120 calls, when the checks were rationed per name).
struct AuthenticatorOptions {
  // Argon2id checks per second (token bucket) for one connection
  // (PresentedCredentials::peer), and the burst it may use at once. A new
  // token over its connection's rate gets UNAVAILABLE without a check
  // (clients retry it); other connections go on.
  double checks_per_second_per_connection = 1.0;
  double check_burst_per_connection = 3.0;
  // The connections that have presented a wrong token, all together: once
  // spent, their new tokens get UNAVAILABLE.
  double checks_per_second = 4.0;
  double check_burst = 8.0;
  // The connections of one address (the peer without its port) that have
  // not presented a wrong token, together: bounds a client that opens a new
  // connection for every wrong secret. A robot's first call after a restart
  // is such a check.
  double clean_checks_per_second_per_address = 8.0;
  double clean_check_burst_per_address = 32.0;
  // The clock (tests inject one).
  std::function<absl::Time()> now = [] { return absl::Now(); };
};

// Thread-safe. A token is checked with Argon2id the first time it is seen
// (one check at a time, within AuthenticatorOptions' rates); the outcome is
// then cached under a keyed BLAKE2b digest of the token (never the token
// itself), so later calls cost a hash lookup. Valid tokens (one per
// principal) and refused ones are cached apart: a flood of junk tokens
// empties only the latter's bounded cache.
class Authenticator {
 public:
  explicit Authenticator(std::vector<CredentialEntry> entries,
                         AuthenticatorOptions options = {});

  // Swaps in a new credentials set (SIGHUP). Cached checks of principals
  // whose name, secret hash and rights are unchanged are kept; every other
  // check is forgotten.
  void Replace(std::vector<CredentialEntry> entries);

  // The principal of a valid token (preferred when both are present) or of
  // the client certificate. UNAUTHENTICATED when neither is presented, or
  // for an unknown or wrong token or an unknown certificate name (the
  // message does not say which part was wrong); UNAVAILABLE for a token
  // not yet checked when its name's (or the server's) check rate is spent.
  absl::StatusOr<Principal> Authenticate(
      const PresentedCredentials& presented) const;

  size_t size() const;

 private:
  struct Set;
  // A token bucket.
  struct Bucket {
    double tokens = 0;
    absl::Time refilled = absl::InfinitePast();
  };
  absl::StatusOr<Principal> CheckToken(const std::shared_ptr<const Set>& set,
                                       const std::string& token,
                                       const std::string& peer) const;
  // Takes one check for a token from connection `peer` (its bucket, and
  // the suspects' or its address's); kRefused (nothing taken) when one is
  // empty.
  enum class Check { kRefused, kClean, kSuspect };
  Check TakeCheck(const std::string& peer) const;
  // Marks `peer` as a connection that presented a wrong token.
  void MarkSuspect(const std::string& peer) const;
  std::shared_ptr<const Set> Current() const;

  const AuthenticatorOptions options_;
  // The key of the cached tokens' digests, for the authenticator's life (so
  // that Replace can keep unchanged principals' checks).
  unsigned char digest_key_[32];
  mutable absl::Mutex mu_;
  // Each set carries its own cache of checked tokens, so a check that ran
  // against an older set can never be cached for a newer one.
  std::shared_ptr<const Set> set_ ABSL_GUARDED_BY(mu_);
  struct Connection {
    Bucket bucket;
    bool suspect = false;
    absl::Time seen = absl::InfinitePast();
  };
  mutable absl::Mutex budget_mu_;
  mutable Bucket suspects_ ABSL_GUARDED_BY(budget_mu_);
  mutable absl::flat_hash_map<std::string, Connection> connections_
      ABSL_GUARDED_BY(budget_mu_);
  mutable absl::flat_hash_map<std::string, Bucket> clean_by_address_
      ABSL_GUARDED_BY(budget_mu_);
  // Held while Argon2id runs: one check at a time.
  mutable absl::Mutex check_mu_;
};

}  // namespace fleetmem::auth

#endif  // FLEETMEM_SERVICES_AUTH_AUTHENTICATOR_H_
