#include "tools/eval/server_child.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <thread>

#include "absl/strings/str_cat.h"

namespace fleetmem::eval {
namespace {

std::string ReadAll(const std::string& path) {
  std::ifstream in(path);
  std::stringstream s;
  s << in.rdbuf();
  return s.str();
}

}  // namespace

ServerChild::~ServerChild() {
  if (pid_ > 0) {
    ::kill(pid_, SIGKILL);
    ::waitpid(pid_, nullptr, 0);
  }
}

absl::Status ServerChild::Start(const std::string& binary,
                                const std::string& data_dir,
                                const std::string& config_file,
                                const std::string& log_file) {
  if (::access(binary.c_str(), X_OK) != 0) {
    return absl::NotFoundError(absl::StrCat("no server binary ", binary));
  }
  const int log = ::open(log_file.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
  if (log < 0)
    return absl::InternalError(absl::StrCat("cannot create ", log_file));
  const pid_t parent = ::getpid();
  const pid_t pid = ::fork();
  if (pid < 0) {
    ::close(log);
    return absl::InternalError("fork failed");
  }
  if (pid == 0) {
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);
    if (::getppid() != parent) ::_exit(127);
    ::dup2(log, STDOUT_FILENO);
    ::dup2(log, STDERR_FILENO);
    ::execl(binary.c_str(), binary.c_str(), "--listen", "127.0.0.1:0",
            "--data-dir", data_dir.c_str(), "--config", config_file.c_str(),
            nullptr);
    ::_exit(127);
  }
  ::close(log);
  pid_ = pid;
  const std::string marker = "listening on ";
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(30);
  while (std::chrono::steady_clock::now() < deadline) {
    int status = 0;
    if (::waitpid(pid_, &status, WNOHANG) == pid_) {
      pid_ = -1;
      return absl::InternalError(
          absl::StrCat("the server exited before listening; its log (",
                       log_file, "):\n", ReadAll(log_file)));
    }
    const std::string out = ReadAll(log_file);
    const size_t at = out.find(marker);
    if (at != std::string::npos) {
      const size_t end = out.find_first_of(" \n", at + marker.size());
      if (end != std::string::npos) {
        address_ = out.substr(at + marker.size(), end - at - marker.size());
        return absl::OkStatus();
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ::kill(pid_, SIGKILL);
  ::waitpid(pid_, nullptr, 0);
  pid_ = -1;
  return absl::DeadlineExceededError(absl::StrCat(
      "the server did not listen within 30 s; its log: ", log_file));
}

absl::Status ServerChild::Stop() {
  if (pid_ <= 0) return absl::OkStatus();
  ::kill(pid_, SIGTERM);
  int status = 0;
  ::waitpid(pid_, &status, 0);
  pid_ = -1;
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
    return absl::InternalError("the server did not exit cleanly on SIGTERM");
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::eval
