// Test-side names for the project's process and file helpers: the server
// child (tools/process/server_process.h) and temporary directories
// (services/common/files.h). Used by the integration tests only.
#ifndef FLEETMEM_TESTS_SERVER_PROCESS_H_
#define FLEETMEM_TESTS_SERVER_PROCESS_H_

#include <string>

#include "services/common/files.h"
#include "tools/process/server_process.h"

namespace fleetmem::testing {

using files::MakeTempDir;
using files::RemoveTree;
using process::DefaultServerBinary;
using process::FreePort;
using process::FreePorts;
using process::NatsClusterOptions;
using process::NatsServerOptions;
using process::ParseListeningPort;
using process::ParseReadyFile;
using process::ServerOptions;
using process::ServerProcess;

// files::TempDir that fails the current test (ADD_FAILURE) if the directory
// cannot be made, and names the tests' directories "fleetmem-it-...".
class TempDir : public files::TempDir {
 public:
  explicit TempDir(const std::string& prefix = "fleetmem-it-");
};

// The contents of `path`, or "" if it cannot be read.
std::string ReadFileOrEmpty(const std::string& path);

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_SERVER_PROCESS_H_
