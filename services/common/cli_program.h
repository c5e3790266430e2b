// CLI11 programs in the one help style of services/common/usage.h: the
// program's own name in every help (not argv[0]), items wrapped to 80
// columns, -h/--help and --version listed in each, defaults shown as given
// (never a path of the build tree: such an option states its default in its
// help instead), and one exit code for a usage error (2, not CLI11's 105
// or 106). Used by every CLI11 program (the server and `fleetmem` format
// their own flags with FormatUsage).
#ifndef FLEETMEM_SERVICES_COMMON_CLI_PROGRAM_H_
#define FLEETMEM_SERVICES_COMMON_CLI_PROGRAM_H_

#include <optional>
#include <string>
#include <string_view>

#include "CLI/CLI.hpp"
#include "services/common/usage.h"

namespace fleetmem::common {

// Lays out a CLI11 App (and its subcommands) with FormatUsage.
class UsageFormatter : public CLI::FormatterBase {
 public:
  std::string make_help(const CLI::App* app, std::string name,
                        CLI::AppFormatMode mode) const override;
};

// Names the program, installs UsageFormatter, -h/--help, --version
// (printing VersionLine) and the exit-status footer. Call before adding
// subcommands (they inherit all of it).
void SetUpProgram(CLI::App& app, std::string_view program);

// Parses the command line: nullopt to go on; otherwise the exit code to
// return at once, after --help or --version (0, printed on stdout) or a
// usage error (kExitUsage, UsageErrorText on stderr).
std::optional<int> ParseProgram(CLI::App& app, int argc, char** argv);

}  // namespace fleetmem::common

#endif  // FLEETMEM_SERVICES_COMMON_CLI_PROGRAM_H_
