#include "services/auth/secret.h"

#include <sodium.h>

#include <string>

#include "absl/status/status.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"

namespace fleetmem::auth {
namespace {

// sodium_init is idempotent and thread-safe; it fails only without a
// randomness source.
absl::Status InitSodium() {
  static const bool ready = sodium_init() >= 0;
  if (!ready) return absl::InternalError("libsodium cannot start");
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::string> NewSecret() {
  if (absl::Status ready = InitSodium(); !ready.ok()) return ready;
  unsigned char bytes[32];
  randombytes_buf(bytes, sizeof bytes);
  char hex[2 * sizeof bytes + 1];
  sodium_bin2hex(hex, sizeof hex, bytes, sizeof bytes);
  return std::string(hex);
}

absl::StatusOr<std::string> HashSecret(absl::string_view secret) {
  if (absl::Status ready = InitSodium(); !ready.ok()) return ready;
  char hash[crypto_pwhash_STRBYTES];
  if (crypto_pwhash_str(hash, secret.data(), secret.size(),
                        crypto_pwhash_OPSLIMIT_INTERACTIVE,
                        crypto_pwhash_MEMLIMIT_INTERACTIVE) != 0) {
    return absl::InternalError("crypto_pwhash_str failed (out of memory?)");
  }
  return std::string(hash);
}

bool VerifySecret(absl::string_view hash, absl::string_view secret) {
  if (!InitSodium().ok()) return false;
  if (hash.size() >= crypto_pwhash_STRBYTES) return false;
  const std::string terminated(hash);  // crypto_pwhash_str_verify wants NUL
  return crypto_pwhash_str_verify(terminated.c_str(), secret.data(),
                                  secret.size()) == 0;
}

absl::Status CheckSecretHash(absl::string_view hash) {
  if (!absl::StartsWith(hash, "$argon2id$") ||
      hash.size() >= crypto_pwhash_STRBYTES) {
    return absl::InvalidArgumentError(
        "secret_hash: not an Argon2id hash string (\"$argon2id$...\", as "
        "fleetmem-credential writes)");
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::auth
