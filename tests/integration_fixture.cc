#include "tests/integration_fixture.h"

#include <sys/stat.h>

#include <fstream>
#include <iostream>

#include "absl/strings/str_cat.h"

namespace fleetmem::testing {
namespace {

// Prints at most the last `limit` characters of the server's output.
void PrintServerLog(const std::string& log_file, size_t limit = 20000) {
  std::string log = ReadFileOrEmpty(log_file);
  if (log.size() > limit) {
    log = absl::StrCat("[... ", log.size() - limit, " bytes cut ...]\n",
                       log.substr(log.size() - limit));
  }
  std::cerr << "---- fleetmem-server output (" << log_file << ") ----\n"
            << log << "\n---- end of server output ----" << std::endl;
}

}  // namespace

void ServerTest::SetUp() {
  ASSERT_FALSE(dir_.path().empty());
  data_dir_ = dir_.Join("data");
  ASSERT_EQ(mkdir(data_dir_.c_str(), 0755), 0) << data_dir_;
  ASSERT_NO_FATAL_FAILURE(StartServer());
}

void ServerTest::TearDown() {
  // Close the test's channel first: with a client still connected the
  // server's graceful shutdown waits for it (see
  // RestartTest.SigtermWithAnIdleClientConnectedExitsCleanly).
  stub_.reset();
  if (server_ != nullptr && server_->running()) {
    absl::StatusOr<int> code = server_->Stop();
    EXPECT_TRUE(code.ok()) << code.status();
    if (code.ok()) {
      EXPECT_EQ(*code, 0) << "fleetmem-server did not exit cleanly on SIGTERM";
    }
  }
  if (HasFailure()) PrintServerLog(dir_.Join("server.log"));
}

void ServerTest::StartServer() {
  ServerOptions options;
  options.data_dir = data_dir_;
  options.log_file = dir_.Join("server.log");
  options.extra_args = server_args_;
  server_ = std::make_unique<ServerProcess>(options);
  ++runs_;
  {
    std::ofstream log(options.log_file, std::ios::app);
    log << "==== test harness: start #" << runs_ << " ====\n";
  }
  absl::Status started = server_->Start();
  ASSERT_TRUE(started.ok()) << started;
  stub_ = MakeStub(server_->address());
}

void ServerTest::KillAndRestart() {
  ASSERT_NE(server_, nullptr);
  server_->Kill();
  ASSERT_NO_FATAL_FAILURE(StartServer());
}

void ServerTest::StopServer() {
  ASSERT_NE(server_, nullptr);
  stub_.reset();  // as in TearDown
  absl::StatusOr<int> code = server_->Stop();
  ASSERT_TRUE(code.ok()) << code.status();
  ASSERT_EQ(*code, 0) << "fleetmem-server did not exit cleanly on SIGTERM";
}

void ServerTest::StopAndRestart() {
  ASSERT_NO_FATAL_FAILURE(StopServer());
  ASSERT_NO_FATAL_FAILURE(StartServer());
}

}  // namespace fleetmem::testing
