// Token secrets: generation, Argon2id hashing and verification (libsodium).
#ifndef FLEETMEM_SERVICES_AUTH_SECRET_H_
#define FLEETMEM_SERVICES_AUTH_SECRET_H_

#include <string>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace fleetmem::auth {

// 32 random bytes from the system's CSPRNG, as 64 hex digits. INTERNAL if
// libsodium cannot start (no randomness source).
absl::StatusOr<std::string> NewSecret();

// libsodium's crypto_pwhash_str (Argon2id, interactive limits: about 0.1 s
// and 64 MiB). INTERNAL if the hash cannot be computed (out of memory).
absl::StatusOr<std::string> HashSecret(absl::string_view secret);

// True if `secret` matches `hash` (a crypto_pwhash_str string); false for a
// wrong secret or a malformed hash.
bool VerifySecret(absl::string_view hash, absl::string_view secret);

// INVALID_ARGUMENT unless `hash` looks like an Argon2id hash string.
absl::Status CheckSecretHash(absl::string_view hash);

}  // namespace fleetmem::auth

#endif  // FLEETMEM_SERVICES_AUTH_SECRET_H_
