// Test utilities: the real fleetmem-server as a child process, and temporary
// directories. Used by the integration tests only.
#ifndef FLEETMEM_TESTS_SERVER_PROCESS_H_
#define FLEETMEM_TESTS_SERVER_PROCESS_H_

#include <sys/types.h>

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <fstream>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fleetmem::testing {

// Path of the server binary built beside the tests
// (FLEETMEM_BIN_DIR "/fleetmem-server").
std::string DefaultServerBinary();

// A new empty directory under $TMPDIR (or /tmp) named `prefix`XXXXXX.
absl::StatusOr<std::string> MakeTempDir(const std::string& prefix);

// Removes `path` and everything below it; a missing path is OK.
absl::Status RemoveTree(const std::string& path);

// A temporary directory removed (recursively) by the destructor, unless the
// environment variable FLEETMEM_KEEP_TEST_DIRS is set.
class TempDir {
 public:
  // Fails the current test (ADD_FAILURE) if the directory cannot be made;
  // path() is empty then.
  explicit TempDir(const std::string& prefix = "fleetmem-it-");
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  const std::string& path() const { return path_; }
  // path() + "/" + name.
  std::string Join(const std::string& name) const;

 private:
  std::string path_;
};

struct ServerOptions {
  // The server binary.
  std::string binary = DefaultServerBinary();
  // --data-dir; must exist (the server may create what is below it).
  std::string data_dir;
  // --config, if not empty.
  std::string config_file;
  // --listen.
  std::string listen = "127.0.0.1:0";
  // The server's stdout and stderr are appended here (created if missing).
  std::string log_file;
  // How long Start() waits for the "listening on" line.
  std::chrono::milliseconds start_timeout{30000};
  // Extra command-line arguments, appended last.
  std::vector<std::string> extra_args;
  // Another server (nats-server): only `binary` and `extra_args` make its
  // command line, and the port is read after `listening_marker`.
  bool fleetmem_flags = true;
  std::string listening_marker = "fleetmem-server listening on ";
};

// nats-server with JetStream on a random loopback port, storing under
// `store_dir`: `/usr/sbin/nats-server` or `/usr/bin/nats-server`, Debian's.
ServerOptions NatsServerOptions(const std::string& store_dir,
                                const std::string& log_file);

// One run of fleetmem-server, started with fork/exec. Its stdout and stderr
// go through one pipe that a reader thread drains into options.log_file (so
// the server can never block on a full pipe) while it looks for the line
// "fleetmem-server listening on HOST:PORT".
//
// The server runs in its own process group and gets SIGKILL if the thread
// that called Start() ends (PR_SET_PDEATHSIG), so a crashed test leaves no
// server behind: call Start() from the test's main thread.
//
// Not thread-safe except where noted; one test thread drives it. The
// destructor kills a server that is still running (SIGKILL) and reaps it.
class ServerProcess {
 public:
  explicit ServerProcess(ServerOptions options);
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  // Starts the binary and waits for the "listening on" line. Errors:
  // NOT_FOUND (no binary), DEADLINE_EXCEEDED (no line within
  // start_timeout; the process is killed), INTERNAL (fork/exec/pipe failed,
  // or the process exited before listening). The message includes the log.
  absl::Status Start();

  // SIGTERM, then waits up to `timeout` for the exit. Returns the exit code
  // (0 = clean), or -signal if a signal ended it; DEADLINE_EXCEEDED if it did
  // not exit in time (it is then SIGKILLed and reaped).
  absl::StatusOr<int> Stop(
      std::chrono::milliseconds timeout = std::chrono::milliseconds(30000));

  // SIGKILL (no clean shutdown) and reap.
  void Kill();

  // Sends `signal` without waiting.
  void Signal(int signal);

  bool running() const { return pid_ > 0; }
  pid_t pid() const { return pid_; }
  int port() const { return port_; }
  // "127.0.0.1:PORT" (loopback, the port the server reported).
  std::string address() const;
  const ServerOptions& options() const { return options_; }

  // Everything the server has written so far. Thread-safe.
  std::string Output() const;

 private:
  void ReadOutput(int fd);
  absl::StatusOr<int> WaitForExit(std::chrono::milliseconds timeout);
  void JoinReader();

  ServerOptions options_;
  pid_t pid_ = -1;
  int port_ = 0;
  std::thread reader_;

  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::string output_;                 // guarded by mu_
  bool reader_done_ = false;           // guarded by mu_
  std::optional<int> listening_port_;  // guarded by mu_
};

// The listening port from a line "`marker`HOST:PORT" anywhere in `output`,
// if there is one.
std::optional<int> ParseListeningPort(
    const std::string& output,
    const std::string& marker = "fleetmem-server listening on ");

// The contents of `path`, or "" if it cannot be read.
std::string ReadFileOrEmpty(const std::string& path);

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_SERVER_PROCESS_H_
