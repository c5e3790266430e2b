// libFuzzer harness: the credentials file through parsing and validation,
// then an authentication by certificate name against what it parsed.
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "services/auth/authenticator.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace auth = fleetmem::auth;
  const std::string text(reinterpret_cast<const char*>(data), size);
  absl::StatusOr<std::vector<auth::CredentialEntry>> entries =
      auth::ParseCredentials(text);
  if (!entries.ok() || entries->empty()) return 0;
  const std::string name = entries->front().certificate_common_name;
  auth::Authenticator authenticator(std::move(*entries));
  authenticator.Authenticate({std::nullopt, name}).IgnoreError();
  return 0;
}
