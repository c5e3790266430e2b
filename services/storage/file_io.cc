#include "services/storage/file_io.h"

#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::storage::file_io {

std::string ErrnoText(int error) { return std::strerror(error); }

absl::Status IoError(int error, std::string_view what) {
  const std::string message = absl::StrCat(V(what), ": ", ErrnoText(error));
  if (error == ENOSPC || error == EDQUOT) {
    return absl::ResourceExhaustedError(message);
  }
  return absl::UnavailableError(message);
}

absl::Status SyncDirectory(const std::string& directory) {
  const int fd = ::open(directory.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd < 0) {
    return IoError(errno, absl::StrCat("open directory '", directory, "'"));
  }
  const int synced = ::fsync(fd);
  const int error = errno;
  ::close(fd);
  if (synced != 0) {
    return IoError(error, absl::StrCat("fsync directory '", directory, "'"));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::storage::file_io
