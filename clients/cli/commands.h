// The subcommands of the `fleetmem` tool, one function each. A command
// validates its flags (usage error: exit 2), makes its call through the C++
// client (server error: exit 1, "error: CODE: message" on stderr) and prints
// the result as a table or, with --json, as protobuf JSON (exit 0).
#ifndef FLEETMEM_CLIENTS_CLI_COMMANDS_H_
#define FLEETMEM_CLIENTS_CLI_COMMANDS_H_

#include <atomic>
#include <functional>
#include <istream>
#include <memory>
#include <ostream>
#include <span>
#include <string>

#include "absl/status/status.h"
#include "clients/cli/flags.h"
#include "clients/cli/printing.h"
#include "clients/cpp/fleetmem_client.h"

namespace fleetmem::cli {

inline constexpr int kExitOk = 0;
inline constexpr int kExitServerError = 1;
inline constexpr int kExitUsage = 2;

// What a command runs with. Pointers are not owned and outlive the call.
struct Invocation {
  // Name of the command, for messages.
  std::string command;
  // Connection settings from the global flags.
  client::ClientOptions client_options;
  // --json: print protobuf JSON instead of tables.
  bool json = false;
  // The command's own flags.
  const FlagValues* flags = nullptr;
  std::istream* in = nullptr;
  std::ostream* out = nullptr;
  std::ostream* err = nullptr;
  // Installs the SIGINT/SIGTERM handlers and returns the flag they set (see
  // CliEnvironment::enable_stop); may be empty.
  std::function<const std::atomic<bool>*()> enable_stop;
};

// A subcommand: its flags and help, and the function that runs it.
struct Command {
  CommandSpec spec;
  int (*run)(const Invocation&) = nullptr;
};

// Every subcommand but `help`, in the order of the help text.
std::span<const Command> Commands();

int RunUpload(const Invocation& invocation);
int RunQuery(const Invocation& invocation);
int RunSample(const Invocation& invocation);
int RunStats(const Invocation& invocation);
int RunHealth(const Invocation& invocation);
int RunConsolidate(const Invocation& invocation);
int RunWatch(const Invocation& invocation);
int RunGenTraces(const Invocation& invocation);
int RunFleets(const Invocation& invocation);
int RunClusters(const Invocation& invocation);
int RunSnapshot(const Invocation& invocation);
int RunExport(const Invocation& invocation);
// import_command.cc
int RunImport(const Invocation& invocation);
int RunDeleteTraces(const Invocation& invocation);
int RunUpdateRewards(const Invocation& invocation);
int RunGetTraces(const Invocation& invocation);
int RunCreateFleet(const Invocation& invocation);
int RunFleet(const Invocation& invocation);
int RunUpdateFleet(const Invocation& invocation);
// alias_commands.cc
int RunDeleteFleet(const Invocation& invocation);
int RunAliases(const Invocation& invocation);
int RunCreateAlias(const Invocation& invocation);
int RunSwitchAlias(const Invocation& invocation);
int RunDeleteAlias(const Invocation& invocation);

// A client of the server the invocation names.
std::unique_ptr<client::Client> Connect(const Invocation& invocation);

// Prints a unary response as JSON or through `print_table`.
template <typename Response, typename PrintTable>
int PrintResponse(const Invocation& invocation, const Response& response,
                  PrintTable print_table) {
  if (invocation.json) {
    PrintJson(response, /*pretty=*/false, *invocation.out);
  } else {
    print_table(response, *invocation.out);
  }
  return kExitOk;
}

// Prints "error: <message>" and a pointer to the help; returns kExitUsage.
int UsageError(const Invocation& invocation, const absl::Status& status);
// Prints "error: CODE: message"; returns kExitServerError.
int ServerError(const Invocation& invocation, const absl::Status& status);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_COMMANDS_H_
