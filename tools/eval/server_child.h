// The real fleetmem-server as a child process of the evaluation: started on
// a free loopback port with its own data directory and configuration file,
// its output in a log file, stopped with SIGTERM. The child gets SIGKILL if
// the evaluation dies (PR_SET_PDEATHSIG), so no server outlives it.
#ifndef FLEETMEM_TOOLS_EVAL_SERVER_CHILD_H_
#define FLEETMEM_TOOLS_EVAL_SERVER_CHILD_H_

#include <sys/types.h>

#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fleetmem::eval {

class ServerChild {
 public:
  ServerChild() = default;
  ~ServerChild();
  ServerChild(const ServerChild&) = delete;
  ServerChild& operator=(const ServerChild&) = delete;

  // Starts `binary --listen 127.0.0.1:0 --data-dir data_dir --config
  // config_file` and waits (30 s at most) for its "listening on" line in
  // `log_file`. NOT_FOUND without the binary; INTERNAL if it exits first;
  // DEADLINE_EXCEEDED if it does not listen in time (it is killed).
  absl::Status Start(const std::string& binary, const std::string& data_dir,
                     const std::string& config_file,
                     const std::string& log_file);
  // SIGTERM and wait for the exit; INTERNAL if it did not exit cleanly.
  absl::Status Stop();
  // "127.0.0.1:PORT".
  const std::string& address() const { return address_; }

 private:
  pid_t pid_ = -1;
  std::string address_;
};

}  // namespace fleetmem::eval

#endif  // FLEETMEM_TOOLS_EVAL_SERVER_CHILD_H_
