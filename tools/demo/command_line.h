// Lets the demo's programs take flags spelled with dashes
// (`--stretch-length 300`) as well as Abseil's underscores.
#ifndef FLEETMEM_TOOLS_DEMO_COMMAND_LINE_H_
#define FLEETMEM_TOOLS_DEMO_COMMAND_LINE_H_

#include <algorithm>
#include <string>
#include <vector>

#include "absl/flags/parse.h"

namespace fleetmem::demo {

// absl::ParseCommandLine after turning '-' into '_' in the name of every
// `--name` or `--name=value` argument (values are left alone). Exits with a
// usage message on an unknown flag, as absl does.
inline void ParseDashedCommandLine(int argc, char** argv) {
  std::vector<std::string> args(argv, argv + argc);
  for (size_t i = 1; i < args.size(); ++i) {
    std::string& arg = args[i];
    if (arg == "--") break;
    if (arg.rfind("--", 0) != 0) continue;
    const size_t end = std::min(arg.find('='), arg.size());
    std::replace(arg.begin() + 2, arg.begin() + end, '-', '_');
  }
  std::vector<char*> pointers;
  for (std::string& arg : args) pointers.push_back(arg.data());
  absl::ParseCommandLine(static_cast<int>(pointers.size()), pointers.data());
}

}  // namespace fleetmem::demo

#endif  // FLEETMEM_TOOLS_DEMO_COMMAND_LINE_H_
