// fleetmem: command-line client of a fleetmem server. See `fleetmem help`.
#include <atomic>
#include <csignal>
#include <cstdlib>
#include <iostream>
#include <string>
#include <vector>

#include "clients/cli/cli.h"

namespace {

std::atomic<bool> stop_requested{false};

extern "C" void RequestStop(int) { stop_requested = true; }

}  // namespace

int main(int argc, char** argv) {
  const std::vector<std::string> args(argv + 1, argv + argc);
  const char* server = std::getenv("FLEETMEM_SERVER");
  fleetmem::cli::CliEnvironment env;
  env.default_server = server != nullptr ? server : "";
  env.in = &std::cin;
  env.out = &std::cout;
  env.err = &std::cerr;
  env.enable_stop = [] {
    std::signal(SIGINT, RequestStop);
    std::signal(SIGTERM, RequestStop);
    return &stop_requested;
  };
  return fleetmem::cli::RunCli(args, env);
}
