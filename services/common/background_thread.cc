#include "services/common/background_thread.h"

#include <pthread.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <string>

#include "absl/strings/str_cat.h"

namespace fleetmem::common {

absl::Status MarkBackgroundThread(std::string_view name, int nice) {
  const std::string short_name(name.substr(0, 15));
  if (const int error = pthread_setname_np(pthread_self(), short_name.c_str());
      error != 0) {
    return absl::InternalError(
        absl::StrCat("naming thread ", short_name, ": ", std::strerror(error)));
  }
  // getpriority and setpriority on a thread id read and set that thread's
  // nice value alone (Linux).
  const auto thread = static_cast<id_t>(syscall(SYS_gettid));
  errno = 0;
  const int current = getpriority(PRIO_PROCESS, thread);
  if (current == -1 && errno != 0) {
    return absl::InternalError(
        absl::StrCat("reading thread priority: ", std::strerror(errno)));
  }
  if (nice <= current) return absl::OkStatus();
  if (setpriority(PRIO_PROCESS, thread, nice) != 0) {
    return absl::InternalError(absl::StrCat("thread ", short_name, " nice ",
                                            nice, ": ", std::strerror(errno)));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::common
