// libFuzzer harness: the CARMEN log parser on arbitrary text.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "clients/robot/sensing/carmen_log.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  fleetmem::robot::ParseCarmenLog(
      std::string_view(reinterpret_cast<const char*>(data), size), "input")
      .IgnoreError();
  return 0;
}
