#include "tools/process/server_process.h"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <fstream>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "absl/strings/strip.h"
#include "absl/synchronization/mutex.h"
#include "fleetmem_paths.h"

namespace fleetmem::process {
namespace {

std::string ErrnoText(const char* what) {
  return absl::StrCat(what, ": ", std::strerror(errno));
}

// The port of "HOST:PORT" if it is in 1..65535.
std::optional<int> PortOf(absl::string_view address) {
  size_t colon = address.rfind(':');
  if (colon == absl::string_view::npos) return std::nullopt;
  int port = 0;
  if (!absl::SimpleAtoi(address.substr(colon + 1), &port) || port <= 0 ||
      port > 65535) {
    return std::nullopt;
  }
  return port;
}

constexpr std::chrono::milliseconds kPoll{20};

}  // namespace

std::string DefaultServerBinary() {
  // Another build's server (e.g. a copy that a rebuild cannot replace
  // while long trials run).
  if (const char* binary = std::getenv("FLEETMEM_SERVER_BINARY");
      binary != nullptr && *binary != '\0') {
    return binary;
  }
#ifdef FLEETMEM_BIN_DIR
  return std::string(FLEETMEM_BIN_DIR) + "/fleetmem-server";
#else
  return "fleetmem-server";
#endif
}

absl::StatusOr<ReadyFile> ParseReadyFile(const std::string& text) {
  ReadyFile ready;
  for (absl::string_view line : absl::StrSplit(text, '\n', absl::SkipEmpty())) {
    std::pair<absl::string_view, absl::string_view> kv =
        absl::StrSplit(line, absl::MaxSplits('=', 1));
    if (kv.first == "grpc" || kv.first == "http") {
      std::optional<int> port = PortOf(kv.second);
      if (!port.has_value()) {
        return absl::InvalidArgumentError(
            absl::StrCat("ready file: bad address in \"", line, "\""));
      }
      (kv.first == "grpc" ? ready.grpc_address : ready.http_address) =
          std::string(kv.second);
      (kv.first == "grpc" ? ready.grpc_port : ready.http_port) = *port;
    } else if (kv.first == "pid") {
      if (!absl::SimpleAtoi(kv.second, &ready.pid)) {
        return absl::InvalidArgumentError(
            absl::StrCat("ready file: bad pid in \"", line, "\""));
      }
    }
  }
  if (ready.grpc_port == 0) {
    return absl::InvalidArgumentError("ready file: no grpc=HOST:PORT line");
  }
  return ready;
}

ServerOptions NatsServerOptions(const std::string& store_dir,
                                const std::string& log_file) {
  ServerOptions options;
  options.binary = access("/usr/sbin/nats-server", X_OK) == 0
                       ? "/usr/sbin/nats-server"
                       : "/usr/bin/nats-server";
  options.fleetmem_flags = false;
  options.listening_marker = "Listening for client connections on ";
  options.log_file = log_file;
  // -p -1: a random free port, which the server logs.
  options.extra_args = {"-a", "127.0.0.1", "-p", "-1", "-js", "-sd", store_dir};
  return options;
}

namespace {

// A socket bound to 127.0.0.1:`port` (0: a port the kernel picks), or -1;
// `port` gets the port bound.
int BindLoopback(int* port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = htons(static_cast<uint16_t>(*port));
  socklen_t size = sizeof(address);
  if (bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) != 0 ||
      getsockname(fd, reinterpret_cast<sockaddr*>(&address), &size) != 0) {
    close(fd);
    return -1;
  }
  *port = ntohs(address.sin_port);
  return fd;
}

// The first port of the kernel's ephemeral range (the source ports of
// outgoing connections); 32768 if it cannot be read.
int EphemeralLow() {
  std::ifstream range("/proc/sys/net/ipv4/ip_local_port_range");
  int low = 0;
  if (!(range >> low) || low <= 0) return 32768;
  return low;
}

}  // namespace

std::vector<int> FreePorts(size_t n) {
  // Every socket stays bound until all are chosen: the kernel hands out
  // one port twice when a socket is closed before the next is bound (a
  // NATS route port given to two servers of one cluster did that).
  //
  // Below the ephemeral range where there is room: a port in it can be
  // taken, before its server binds it, by the source port of any outgoing
  // connection — even one to that very port (TCP's self-connect: a NATS
  // server dialling a peer's route port before the peer listened got that
  // port as its own source, connected to itself, and the peer could not
  // bind it; 1 run of the cluster test in 50).
  //
  // Calls of one process go on from where the last one stopped (a port
  // handed out and closed is free again until its server binds it); the
  // first starts at a point of the process id, so that processes running
  // at once start apart.
  ABSL_CONST_INIT static absl::Mutex mu(absl::kConstInit);
  static int next = 0;  // guarded by mu
  std::vector<int> fds;
  std::vector<int> ports;
  const int high = EphemeralLow() - 1;
  const int low = 10000;
  if (high - low >= 1000) {
    const int span = high - low + 1;
    absl::MutexLock lock(&mu);
    if (next < low || next > high) {
      next = low + static_cast<int>((static_cast<unsigned>(getpid()) * 7919u) %
                                    static_cast<unsigned>(span));
    }
    for (int tried = 0; tried < span && ports.size() < n; ++tried) {
      int port = next;
      next = next == high ? low : next + 1;
      const int fd = BindLoopback(&port);
      if (fd < 0) continue;
      fds.push_back(fd);
      ports.push_back(port);
    }
  }
  while (ports.size() < n) {  // no room below the range: the kernel's pick
    int port = 0;
    const int fd = BindLoopback(&port);
    if (fd >= 0) fds.push_back(fd);
    ports.push_back(fd >= 0 ? port : 0);
  }
  for (int fd : fds) close(fd);
  return ports;
}

int FreePort() { return FreePorts(1)[0]; }

std::vector<ServerOptions> NatsClusterOptions(const std::string& dir, int n) {
  const std::vector<int> routes = FreePorts(n);
  std::string all_routes;
  for (int port : routes) {
    absl::StrAppend(&all_routes, all_routes.empty() ? "" : ",",
                    "nats://127.0.0.1:", port);
  }
  std::vector<ServerOptions> servers;
  for (int i = 0; i < n; ++i) {
    ServerOptions options =
        NatsServerOptions(absl::StrCat(dir, "/jetstream-", i),
                          absl::StrCat(dir, "/nats-", i, ".log"));
    options.extra_args.insert(
        options.extra_args.end(),
        {"-n", absl::StrCat("nats-", i), "--cluster_name", "fleetmem",
         "--cluster", absl::StrCat("nats://127.0.0.1:", routes[i]), "--routes",
         all_routes});
    servers.push_back(std::move(options));
  }
  return servers;
}

std::optional<int> ParseListeningPort(const std::string& output,
                                      const std::string& marker) {
  size_t at = output.find(marker);
  if (at == std::string::npos) return std::nullopt;
  size_t begin = at + marker.size();
  size_t end = output.find_first_of("\r\n", begin);
  if (end == std::string::npos) return std::nullopt;  // line not complete
  const std::string line = output.substr(begin, end - begin);
  return PortOf(absl::StripTrailingAsciiWhitespace(line));
}

ServerProcess::ServerProcess(ServerOptions options)
    : options_(std::move(options)) {}

ServerProcess::~ServerProcess() {
  if (running()) Kill();
  JoinReader();
}

std::string ServerProcess::address() const {
  return absl::StrCat("127.0.0.1:", port_);
}

std::string ServerProcess::Output() const {
  std::lock_guard<std::mutex> lock(mu_);
  return output_;
}

std::optional<int> ServerProcess::ReadyPort() {
  if (!options_.fleetmem_flags) {
    std::lock_guard<std::mutex> lock(mu_);
    return listening_port_;
  }
  absl::StatusOr<std::string> text = files::ReadFile(ready_dir_.Join("ready"));
  if (!text.ok()) return std::nullopt;
  // Written by rename: complete whenever it exists.
  absl::StatusOr<ReadyFile> ready = ParseReadyFile(*text);
  if (!ready.ok()) return std::nullopt;
  http_address_ = ready->http_address;
  return ready->grpc_port;
}

std::vector<std::string> ServerProcess::CommandLine(
    const std::string& ready_file) const {
  std::vector<std::string> args = {options_.binary};
  if (options_.fleetmem_flags) {
    args.insert(args.end(), {"--listen", options_.listen, "--data-dir",
                             options_.data_dir, "--ready-file", ready_file});
    if (!options_.config_file.empty()) {
      args.insert(args.end(), {"--config", options_.config_file});
    }
  }
  args.insert(args.end(), options_.extra_args.begin(),
              options_.extra_args.end());
  return args;
}

absl::Status ServerProcess::Spawn(std::vector<std::string>& args) {
  // Everything the child needs is prepared before fork(): after fork() in a
  // threaded process only async-signal-safe calls are allowed.
  std::vector<char*> argv;
  for (std::string& arg : args) argv.push_back(arg.data());
  argv.push_back(nullptr);

  int fds[2];
  if (pipe2(fds, O_CLOEXEC) != 0)
    return absl::InternalError(ErrnoText("pipe2"));
  const pid_t parent = getpid();
  pid_t pid = fork();
  if (pid < 0) {
    close(fds[0]);
    close(fds[1]);
    return absl::InternalError(ErrnoText("fork"));
  }
  if (pid == 0) {
    // Child: stdout and stderr into the pipe; die with the caller. Own
    // process group, so that Kill() also ends anything it started.
    setpgid(0, 0);
    prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (getppid() != parent) _exit(127);
    dup2(fds[1], STDOUT_FILENO);
    dup2(fds[1], STDERR_FILENO);
    int devnull = open("/dev/null", O_RDONLY);
    if (devnull >= 0) dup2(devnull, STDIN_FILENO);
    execv(argv[0], argv.data());
    static const char kExecFailed[] = "exec of the server failed\n";
    ssize_t ignored =
        write(STDERR_FILENO, kExecFailed, sizeof(kExecFailed) - 1);
    (void)ignored;
    _exit(127);
  }
  close(fds[1]);
  pid_ = pid;
  reader_ = std::thread([this, fd = fds[0]] { ReadOutput(fd); });
  return absl::OkStatus();
}

absl::Status ServerProcess::Start() {
  if (running()) return absl::FailedPreconditionError("already running");
  if (access(options_.binary.c_str(), X_OK) != 0) {
    return absl::NotFoundError(absl::StrCat(
        "server binary not found or not executable: ", options_.binary,
        " (build target fleetmem-server)"));
  }
  if (!ready_dir_.status().ok()) return ready_dir_.status();
  JoinReader();  // from an earlier run
  {
    std::lock_guard<std::mutex> lock(mu_);
    output_.clear();
    reader_done_ = false;
    listening_port_.reset();
  }
  port_ = 0;
  http_address_.clear();
  const std::string ready_file = ready_dir_.Join("ready");
  files::RemoveTree(ready_file).IgnoreError();

  std::vector<std::string> args = CommandLine(ready_file);
  if (absl::Status spawned = Spawn(args); !spawned.ok()) return spawned;

  const auto give_up =
      std::chrono::steady_clock::now() + options_.start_timeout;
  bool exited = false;
  while (true) {
    if (std::optional<int> port = ReadyPort(); port.has_value()) {
      port_ = *port;
      return absl::OkStatus();
    }
    if (exited || std::chrono::steady_clock::now() >= give_up) break;
    std::unique_lock<std::mutex> lock(mu_);
    // Woken early by output (a marker line) or the end of output.
    cv_.wait_for(lock, kPoll);
    // One more look for the file after the output ended: a server may
    // write it and exit at once.
    exited = reader_done_;
  }
  // Either the process closed its output (it exited) or it was too slow.
  const bool timed_out = !exited;
  if (timed_out) {
    Kill();
  } else {
    absl::StatusOr<int> code = WaitForExit(std::chrono::milliseconds(5000));
    if (!code.ok()) Kill();
  }
  JoinReader();
  std::string message = absl::StrCat(
      timed_out ? "the server was not ready within "
                : "the server ended its output before it was ready; ",
      timed_out ? absl::StrCat(options_.start_timeout.count(), " ms; ") : "",
      "command: ", absl::StrJoin(args, " "), "\n--- server output ---\n",
      Output());
  return timed_out ? absl::DeadlineExceededError(message)
                   : absl::InternalError(message);
}

void ServerProcess::ReadOutput(int fd) {
  std::ofstream log;
  if (!options_.log_file.empty()) {
    log.open(options_.log_file, std::ios::app | std::ios::binary);
  }
  char buffer[4096];
  while (true) {
    ssize_t n = read(fd, buffer, sizeof(buffer));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;
    if (log.is_open()) {
      log.write(buffer, n);
      log.flush();
    }
    std::lock_guard<std::mutex> lock(mu_);
    output_.append(buffer, static_cast<size_t>(n));
    if (!options_.fleetmem_flags && !listening_port_.has_value()) {
      listening_port_ = ParseListeningPort(output_, options_.listening_marker);
      if (listening_port_.has_value()) cv_.notify_all();
    }
  }
  close(fd);
  std::lock_guard<std::mutex> lock(mu_);
  reader_done_ = true;
  cv_.notify_all();
}

void ServerProcess::JoinReader() {
  if (reader_.joinable()) reader_.join();
}

absl::StatusOr<int> ServerProcess::WaitForExit(
    std::chrono::milliseconds timeout) {
  if (!running()) return absl::FailedPreconditionError("not running");
  const auto give_up = std::chrono::steady_clock::now() + timeout;
  while (true) {
    int status = 0;
    pid_t done = waitpid(pid_, &status, WNOHANG);
    if (done == pid_) {
      pid_ = -1;
      if (WIFEXITED(status)) return WEXITSTATUS(status);
      if (WIFSIGNALED(status)) return -WTERMSIG(status);
      return absl::InternalError("unexpected wait status");
    }
    if (done < 0 && errno != EINTR) {
      pid_ = -1;
      return absl::InternalError(ErrnoText("waitpid"));
    }
    if (std::chrono::steady_clock::now() >= give_up) {
      return absl::DeadlineExceededError(absl::StrCat("the server (pid ", pid_,
                                                      ") did not exit within ",
                                                      timeout.count(), " ms"));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
}

absl::StatusOr<int> ServerProcess::Stop(std::chrono::milliseconds timeout) {
  if (!running()) return absl::FailedPreconditionError("not running");
  kill(pid_, SIGTERM);
  absl::StatusOr<int> code = WaitForExit(timeout);
  if (!code.ok() && running()) Kill();
  JoinReader();
  return code;
}

void ServerProcess::Kill() {
  if (!running()) return;
  kill(-pid_, SIGKILL);  // the server's process group (see Start)
  kill(pid_, SIGKILL);
  int status = 0;
  while (waitpid(pid_, &status, 0) < 0 && errno == EINTR) {
  }
  pid_ = -1;
  JoinReader();
}

void ServerProcess::Signal(int signal) {
  if (running()) kill(pid_, signal);
}

}  // namespace fleetmem::process
