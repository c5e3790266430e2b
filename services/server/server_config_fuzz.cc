// libFuzzer harness: the server's config file (text format) through parsing
// and validation.
#include <cstddef>
#include <cstdint>
#include <string>

#include "services/server/server_config.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  fleetmem::server::ServerConfig config;
  const std::string text(reinterpret_cast<const char*>(data), size);
  if (!fleetmem::server::ApplyConfigText(text, &config).ok()) return 0;
  fleetmem::server::ValidateServerConfig(config).IgnoreError();
  fleetmem::server::DescribeConfig(config);
  return 0;
}
