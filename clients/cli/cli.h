// The `fleetmem` tool as a function of its arguments and streams, so that
// tests can run it without a process: global flags, help, dispatch to the
// subcommands of commands.h.
#ifndef FLEETMEM_CLIENTS_CLI_CLI_H_
#define FLEETMEM_CLIENTS_CLI_CLI_H_

#include <atomic>
#include <functional>
#include <istream>
#include <ostream>
#include <span>
#include <string>

namespace fleetmem::cli {

// What the tool gets from its process. Pointers are not owned.
struct CliEnvironment {
  // Server address when --server is not given (main reads FLEETMEM_SERVER;
  // empty means 127.0.0.1:50051).
  std::string default_server;
  std::istream* in = nullptr;
  std::ostream* out = nullptr;
  std::ostream* err = nullptr;
  // Called by a command that ends gracefully on Ctrl-C (watch): installs the
  // signal handlers and returns the flag they set. Other commands keep the
  // default signal behaviour. May be empty (no graceful stop).
  std::function<const std::atomic<bool>*()> enable_stop;
};

// Runs `fleetmem` with `args` (argv without the program name). Returns the
// exit status: 0 success, 1 server error, 2 usage or input error.
int RunCli(std::span<const std::string> args, const CliEnvironment& env);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_CLI_H_
