// gtest fixture for integration tests: a fresh data directory and a real
// fleetmem-server on loopback, with a generated stub to talk to it.
#ifndef FLEETMEM_TESTS_INTEGRATION_FIXTURE_H_
#define FLEETMEM_TESTS_INTEGRATION_FIXTURE_H_

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "fleetmem/v1/memory.grpc.pb.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
#include "tests/server_process.h"

namespace fleetmem::testing {

// Starts the server in SetUp; in TearDown drops stub(), stops the server
// with SIGTERM and expects exit code 0 (so every test also checks a clean
// shutdown), then prints the server's output if the test failed.
class ServerTest : public ::testing::Test {
 protected:
  void SetUp() override;
  void TearDown() override;

  // Starts a server on data_dir() (fatal failure if it cannot start) and
  // points stub() at it.
  void StartServer();
  // SIGKILL (no clean shutdown), then StartServer() on the same data dir.
  void KillAndRestart();
  // SIGTERM and expect exit code 0, then StartServer() on the same data dir.
  void StopAndRestart();
  // Drops stub() (closing its channel), then SIGTERM; expects exit code 0.
  void StopServer();
  // Arguments every later StartServer() appends (e.g. --config FILE).
  void set_server_args(std::vector<std::string> args) {
    server_args_ = std::move(args);
  }

  v1::MemoryService::Stub& stub() { return *stub_; }
  ServerProcess& server() { return *server_; }
  const std::string& data_dir() const { return data_dir_; }
  const TempDir& temp_dir() const { return dir_; }

 private:
  TempDir dir_;
  std::string data_dir_;
  int runs_ = 0;
  std::vector<std::string> server_args_;
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<v1::MemoryService::Stub> stub_;
};

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_INTEGRATION_FIXTURE_H_
