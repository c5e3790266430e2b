// Command-line parsing of the `fleetmem` tool: `fleetmem [global flags]
// <command> [flags]`, flags as `--name value` or `--name=value`. Parsing only:
// no I/O, no environment.
#ifndef FLEETMEM_CLIENTS_CLI_FLAGS_H_
#define FLEETMEM_CLIENTS_CLI_FLAGS_H_

#include <cstdint>
#include <functional>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace fleetmem::cli {

// A flag a command (or the tool) accepts.
struct FlagSpec {
  // Name without the leading "--", e.g. "fleet".
  std::string name;
  // Placeholder of the value in help, e.g. "ID"; empty for a boolean flag.
  std::string value_name;
  // One line of help.
  std::string help;
};

// A subcommand: its flags and help.
struct CommandSpec {
  // Name on the command line, e.g. "upload".
  std::string name;
  // Arguments after the name in the usage line, e.g. "--fleet ID".
  std::string synopsis;
  // One line for the command list of `fleetmem help`.
  std::string summary;
  // Paragraphs for `fleetmem <name> --help` (may be empty).
  std::string description;
  std::vector<FlagSpec> flags;
};

// Flag values given on a command line. Getters return INVALID_ARGUMENT
// naming the flag when a value is missing or malformed.
class FlagValues {
 public:
  void Set(absl::string_view name, std::string value);
  bool Has(absl::string_view name) const;

  // The value of a required flag.
  absl::StatusOr<std::string> Required(absl::string_view name) const;
  std::string StringOr(absl::string_view name, std::string fallback) const;
  // Non-negative integer in [0, max]; `fallback` when the flag is absent.
  absl::StatusOr<uint64_t> UintOr(absl::string_view name, uint64_t fallback,
                                  uint64_t max = UINT64_MAX) const;
  absl::StatusOr<uint64_t> RequiredUint(absl::string_view name,
                                        uint64_t max = UINT64_MAX) const;
  // Finite number.
  absl::StatusOr<double> RequiredDouble(absl::string_view name) const;
  // Comma- or space-separated finite numbers.
  absl::StatusOr<std::vector<double>> RequiredList(
      absl::string_view name) const;

 private:
  std::map<std::string, std::string, std::less<>> values_;
};

// A parsed command line.
struct CommandLine {
  // The subcommand; empty when none was given.
  std::string command;
  // Words after the command that are not flags (e.g. `help upload`).
  std::vector<std::string> positional;
  // Global flags (allowed before or after the command).
  FlagValues global;
  // The command's own flags (only after the command).
  FlagValues flags;
  // --help or -h was given.
  bool help = false;
};

// Parses `args` (argv without the program name). `commands` lists the known
// subcommands; an unknown command, an unknown flag or a flag without its value
// is INVALID_ARGUMENT with a message for the user.
absl::StatusOr<CommandLine> ParseCommandLine(
    std::span<const std::string> args, std::span<const FlagSpec> global_flags,
    std::span<const CommandSpec> commands);

// Numbers separated by commas and/or whitespace; INVALID_ARGUMENT naming
// `what` for an empty list or a word that is not a finite number.
absl::StatusOr<std::vector<double>> ParseNumberList(absl::string_view text,
                                                    absl::string_view what);

// Help texts.
std::string FormatToolHelp(std::span<const FlagSpec> global_flags,
                           std::span<const CommandSpec> commands);
std::string FormatCommandHelp(const CommandSpec& command,
                              std::span<const FlagSpec> global_flags);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_FLAGS_H_
