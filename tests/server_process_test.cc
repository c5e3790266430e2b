// Tests of the test utilities themselves, with shell scripts standing in for
// the server binary.
#include "tests/server_process.h"

#include <sys/stat.h>

#include <fstream>
#include <optional>
#include <string>

#include "absl/strings/match.h"
#include "gtest/gtest.h"

namespace fleetmem::testing {
namespace {

using process::ReadyFile;

TEST(ParseReadyFileTest, ReadsTheAddressesAndRefusesWhatIsNotOne) {
  absl::StatusOr<ReadyFile> ready =
      ParseReadyFile("grpc=127.0.0.1:4242\nhttp=[::1]:8080\npid=77\n");
  ASSERT_TRUE(ready.ok()) << ready.status();
  EXPECT_EQ(ready->grpc_address, "127.0.0.1:4242");
  EXPECT_EQ(ready->grpc_port, 4242);
  EXPECT_EQ(ready->http_address, "[::1]:8080");
  EXPECT_EQ(ready->http_port, 8080);
  EXPECT_EQ(ready->pid, 77);
  ready = ParseReadyFile("pid=1\ngrpc=h:1");
  ASSERT_TRUE(ready.ok()) << ready.status();
  EXPECT_TRUE(ready->http_address.empty());
  for (const char* bad :
       {"", "pid=3\n", "grpc=127.0.0.1:0\n", "grpc=127.0.0.1:http\n",
        "grpc=h:70000\n", "grpc=h:1\nhttp=h\n", "grpc=h:1\npid=x\n"}) {
    EXPECT_EQ(ParseReadyFile(bad).status().code(),
              absl::StatusCode::kInvalidArgument)
        << bad;
  }
}

TEST(ParseListeningPortTest, FindsThePortOfACompleteLine) {
  const std::string marker = "Listening for client connections on ";
  struct Case {
    std::string output;
    std::optional<int> port;
  };
  const Case cases[] = {
      {marker + "127.0.0.1:4242\n", 4242},
      {"I0101 log\n[1] " + marker + "[::1]:50051\r\nmore", 50051},
      {marker + "0.0.0.0:1 \n", 1},
      {marker + "127.0.0.1:4242", std::nullopt},
      {marker + "127.0.0.1:0\n", std::nullopt},
      {marker + "127.0.0.1:70000\n", std::nullopt},
      {"Listening on 127.0.0.1:4242\n", std::nullopt},
      {"", std::nullopt},
  };
  for (const Case& c : cases) {
    EXPECT_EQ(ParseListeningPort(c.output, marker), c.port) << c.output;
  }
}

class ServerProcessTest : public ::testing::Test {
 protected:
  // An executable shell script `name` in the temporary directory. `body`
  // may call `ready ADDRESS` to write the --ready-file as the server does.
  std::string Script(const std::string& name, const std::string& body) {
    std::string path = dir_.Join(name);
    std::ofstream(path) << "#!/bin/sh\n"
                        << "for a; do [ \"$prev\" = --ready-file ] && "
                           "file=$a; prev=$a; done\n"
                        << "ready() { echo \"grpc=$1\" >\"$file.tmp\" && "
                           "mv \"$file.tmp\" \"$file\"; }\n"
                        << body << "\n";
    EXPECT_EQ(chmod(path.c_str(), 0755), 0);
    return path;
  }
  ServerOptions Options(const std::string& binary) {
    ServerOptions options;
    options.binary = binary;
    options.data_dir = dir_.Join("data");
    options.log_file = dir_.Join("server.log");
    options.start_timeout = std::chrono::milliseconds(5000);
    return options;
  }
  TempDir dir_;
};

TEST_F(ServerProcessTest, StartsStopsAndLogs) {
  ServerProcess server(Options(Script("ok.sh",
                                      "trap 'echo bye; exit 0' TERM\n"
                                      "echo \"args: $*\"\n"
                                      "ready 127.0.0.1:4242\n"
                                      "while true; do sleep 0.05; done")));
  ASSERT_TRUE(server.Start().ok());
  EXPECT_TRUE(server.running());
  EXPECT_EQ(server.port(), 4242);
  EXPECT_EQ(server.address(), "127.0.0.1:4242");
  absl::StatusOr<int> code = server.Stop();
  ASSERT_TRUE(code.ok()) << code.status();
  EXPECT_EQ(*code, 0);
  EXPECT_FALSE(server.running());
  const std::string log = ReadFileOrEmpty(dir_.Join("server.log"));
  EXPECT_TRUE(absl::StrContains(log, "args: --listen 127.0.0.1:0 --data-dir " +
                                         dir_.Join("data") + " --ready-file "))
      << log;
  EXPECT_TRUE(absl::StrContains(log, "bye")) << log;
  EXPECT_EQ(server.Output(), log);
}

TEST_F(ServerProcessTest, PassesTheConfigFile) {
  ServerOptions options = Options(
      Script("config.sh", "echo \"args: $*\"; ready h:7; exec sleep 30"));
  options.config_file = "/some/config.yaml";
  ServerProcess server(options);
  ASSERT_TRUE(server.Start().ok());
  server.Kill();  // joins the output's reader: Output() is complete after it
  EXPECT_FALSE(server.running());
  EXPECT_TRUE(absl::StrContains(server.Output(), "--config /some/config.yaml"));
}

TEST_F(ServerProcessTest, ReportsAServerThatExitsBeforeListening) {
  ServerProcess server(
      Options(Script("fail.sh", "echo 'cannot open data dir'; exit 3")));
  absl::Status status = server.Start();
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal) << status;
  EXPECT_TRUE(absl::StrContains(status.message(), "cannot open data dir"))
      << status;
  EXPECT_FALSE(server.running());
}

TEST_F(ServerProcessTest, TimesOutOnAServerThatNeverGetsReady) {
  // A log line is no readiness signal: only the ready file is.
  ServerOptions options = Options(Script(
      "silent.sh",
      "echo 'starting'; echo 'fleetmem-server listening on 127.0.0.1:1'; "
      "exec sleep 30"));
  options.start_timeout = std::chrono::milliseconds(300);
  ServerProcess server(options);
  absl::Status status = server.Start();
  EXPECT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
  EXPECT_TRUE(absl::StrContains(status.message(), "starting")) << status;
  EXPECT_FALSE(server.running());
}

TEST_F(ServerProcessTest, StopGivesUpOnAServerIgnoringSigterm) {
  ServerProcess server(Options(Script("stubborn.sh",
                                      "trap '' TERM\n"
                                      "ready [::1]:5151\n"
                                      "exec sleep 30")));
  ASSERT_TRUE(server.Start().ok());
  EXPECT_EQ(server.port(), 5151);
  absl::StatusOr<int> code = server.Stop(std::chrono::milliseconds(200));
  EXPECT_EQ(code.status().code(), absl::StatusCode::kDeadlineExceeded);
  EXPECT_FALSE(server.running());
}

TEST_F(ServerProcessTest, MissingBinaryIsNotFound) {
  ServerProcess server(Options(dir_.Join("no-such-binary")));
  EXPECT_EQ(server.Start().code(), absl::StatusCode::kNotFound);
}

TEST_F(ServerProcessTest, StartsTheRealServerAndReadsItsPorts) {
  ServerOptions options = Options(DefaultServerBinary());
  options.extra_args = {"--http-listen", "127.0.0.1:0"};
  ServerProcess server(options);
  ASSERT_TRUE(server.Start().ok());
  EXPECT_GT(server.port(), 0);
  EXPECT_TRUE(absl::StartsWith(server.http_address(), "127.0.0.1:"))
      << server.http_address();
  EXPECT_NE(server.http_address(), "127.0.0.1:0");
  absl::StatusOr<int> code = server.Stop();
  ASSERT_TRUE(code.ok()) << code.status();
  EXPECT_EQ(*code, 0);
}

// A second server on a port in use, or on a data directory in use, exits
// with a clear error and leaves the first one alone, 10 times each (the outside
// sweep: a second server bound the port too, SO_REUSEPORT, and the kernel split
// the calls between the two).
TEST_F(ServerProcessTest, ASecondServerOnAPortOrDataDirInUseExits) {
  ServerOptions first_options = Options(DefaultServerBinary());
  first_options.extra_args = {"--http-listen", "127.0.0.1:0"};
  ServerProcess first(first_options);
  ASSERT_TRUE(first.Start().ok()) << first.Output();
  struct Case {
    std::string name, data_dir, listen, http_listen, expected;
  };
  const std::vector<Case> cases = {
      {"grpc port", dir_.Join("data-2"), first.address(), "127.0.0.1:0",
       "cannot listen on " + first.address()},
      {"http port", dir_.Join("data-3"), "127.0.0.1:0", first.http_address(),
       "cannot listen for HTTP on " + first.http_address()},
      {"data dir", first_options.data_dir, "127.0.0.1:0", "127.0.0.1:0",
       "is in use by another process"},
  };
  for (int attempt = 0; attempt < 10; ++attempt) {
    for (const Case& c : cases) {
      SCOPED_TRACE(absl::StrCat(c.name, ", attempt ", attempt));
      ServerOptions options = Options(DefaultServerBinary());
      options.data_dir = c.data_dir;
      options.listen = c.listen;
      options.log_file = dir_.Join("second.log");
      options.extra_args = {"--http-listen", c.http_listen};
      ServerProcess second(options);
      const absl::Status started = second.Start();
      EXPECT_EQ(started.code(), absl::StatusCode::kInternal) << started;
      EXPECT_TRUE(absl::StrContains(started.message(), c.expected)) << started;
      EXPECT_FALSE(second.running());
    }
  }
  EXPECT_TRUE(first.running());
  absl::StatusOr<int> code = first.Stop();
  ASSERT_TRUE(code.ok()) << code.status();
  EXPECT_EQ(*code, 0);
}

TEST(TempDirTest, MakesAndRemovesADirectory) {
  std::string path;
  {
    TempDir dir("fleetmem-tempdir-test-");
    path = dir.path();
    struct stat info;
    ASSERT_EQ(stat(path.c_str(), &info), 0);
    EXPECT_TRUE(S_ISDIR(info.st_mode));
    ASSERT_EQ(mkdir(dir.Join("sub").c_str(), 0755), 0);
    std::ofstream(dir.Join("sub/file")) << "x";
  }
  if (std::getenv("FLEETMEM_KEEP_TEST_DIRS") == nullptr) {
    struct stat info;
    EXPECT_NE(stat(path.c_str(), &info), 0) << path << " still exists";
  }
}

}  // namespace
}  // namespace fleetmem::testing
