// The real fleetmem-server (or another server, such as nats-server) as a
// child process: the one way the integration tests, the evaluations and the
// benchmarks' C++ code start a server. Its shell twin is
// tools/process/server.sh. Both wait for the server's documented readiness
// signal, the --ready-file (services/server/server_config.h), never for a
// log line or a fixed time.
#ifndef FLEETMEM_TOOLS_PROCESS_SERVER_PROCESS_H_
#define FLEETMEM_TOOLS_PROCESS_SERVER_PROCESS_H_

#include <sys/types.h>

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/common/files.h"

namespace fleetmem::process {

// Path of the server binary: $FLEETMEM_SERVER_BINARY if set, else this
// build's (FLEETMEM_BIN_DIR "/fleetmem-server").
std::string DefaultServerBinary();

// What a fleetmem-server's --ready-file says.
struct ReadyFile {
  std::string grpc_address;  // "HOST:PORT", always present
  int grpc_port = 0;
  std::string http_address;  // empty without --http-listen
  int http_port = 0;
  int pid = 0;
};

// Parses the text of a ready file; INVALID_ARGUMENT unless it has a
// grpc=HOST:PORT line with a port in 1..65535 (and a valid one in any
// http= line).
absl::StatusOr<ReadyFile> ParseReadyFile(const std::string& text);

struct ServerOptions {
  // The server binary.
  std::string binary = DefaultServerBinary();
  // --data-dir; the server creates it if missing.
  std::string data_dir;
  // --config, if not empty.
  std::string config_file;
  // --listen.
  std::string listen = "127.0.0.1:0";
  // The server's stdout and stderr are appended here (created if missing).
  std::string log_file;
  // How long Start() waits for the server to be ready.
  std::chrono::milliseconds start_timeout{60000};
  // Extra command-line arguments, appended last.
  std::vector<std::string> extra_args;
  // Another server (nats-server): only `binary` and `extra_args` make its
  // command line, and it is ready when its output has a line
  // "`listening_marker`HOST:PORT" (no --ready-file).
  bool fleetmem_flags = true;
  std::string listening_marker;
};

// nats-server with JetStream on a random loopback port, storing under
// `store_dir`: `/usr/sbin/nats-server` or `/usr/bin/nats-server`, Debian's.
ServerOptions NatsServerOptions(const std::string& store_dir,
                                const std::string& log_file);

// A loopback port that was free a moment ago (for servers that need a
// fixed port: replicas, whose addresses are their ids, and NATS routes).
int FreePort();
// `n` such ports, all different.
std::vector<int> FreePorts(size_t n);

// `n` nats-servers routed into one JetStream cluster ("fleetmem"), server i
// storing under `dir`/jetstream-i and logging to `dir`/nats-i.log. Start
// them all, then wait for each (each waits for its routes once it listens).
std::vector<ServerOptions> NatsClusterOptions(const std::string& dir, int n);

// One run of a server, started with fork/exec. Its stdout and stderr go
// through one pipe that a reader thread drains into options.log_file (so the
// server can never block on a full pipe). A fleetmem-server gets
// `--ready-file` in a private temporary directory, and Start() returns once
// that file appears.
//
// The server runs in its own process group and gets SIGKILL if the thread
// that called Start() ends (PR_SET_PDEATHSIG), so a crashed caller leaves
// no server behind: call Start() from the main thread.
//
// Not thread-safe except where noted; one thread drives it. The destructor
// kills a server that is still running (SIGKILL) and reaps it.
class ServerProcess {
 public:
  explicit ServerProcess(ServerOptions options);
  ~ServerProcess();
  ServerProcess(const ServerProcess&) = delete;
  ServerProcess& operator=(const ServerProcess&) = delete;

  // Starts the binary and waits until it is ready. Errors: NOT_FOUND (no
  // binary), DEADLINE_EXCEEDED (not ready within start_timeout; the process
  // is killed), INTERNAL (fork/exec/pipe failed, or the process exited
  // before it was ready). The message includes the server's output.
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
  // The HTTP port's "HOST:PORT" from the ready file; empty without one.
  const std::string& http_address() const { return http_address_; }
  const ServerOptions& options() const { return options_; }

  // Everything the server has written so far. Thread-safe.
  std::string Output() const;

 private:
  // The server's arguments (argv[0] the binary), its ready file
  // `ready_file`.
  std::vector<std::string> CommandLine(const std::string& ready_file) const;
  // Starts the server with `args` (their bytes become its argv), its
  // output read by reader_.
  absl::Status Spawn(std::vector<std::string>& args);
  void ReadOutput(int fd);
  absl::StatusOr<int> WaitForExit(std::chrono::milliseconds timeout);
  void JoinReader();
  // The port once the server is ready (ready file or marker), if it is.
  std::optional<int> ReadyPort();

  ServerOptions options_;
  files::TempDir ready_dir_{"fleetmem-ready-"};
  pid_t pid_ = -1;
  int port_ = 0;
  std::string http_address_;
  std::thread reader_;

  mutable std::mutex mu_;
  std::condition_variable cv_;
  std::string output_;                 // guarded by mu_
  bool reader_done_ = false;           // guarded by mu_
  std::optional<int> listening_port_;  // guarded by mu_ (marker servers)
};

// The listening port from a line "`marker`HOST:PORT" anywhere in `output`,
// if there is one (servers other than fleetmem-server).
std::optional<int> ParseListeningPort(const std::string& output,
                                      const std::string& marker);

}  // namespace fleetmem::process

#endif  // FLEETMEM_TOOLS_PROCESS_SERVER_PROCESS_H_
