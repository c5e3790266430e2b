// Whole files in and out: config and credentials files, the robot's sources
// (images, logs), the evaluations' text outputs, test inputs. The one copy
// of this for the whole project (servers, clients, tools and tests): it has
// no project dependency, so clients may link it as they link core.
#ifndef FLEETMEM_SERVICES_COMMON_FILES_H_
#define FLEETMEM_SERVICES_COMMON_FILES_H_

#include <cstdint>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"

namespace fleetmem::files {

// NOT_FOUND naming `path` if it cannot be opened, DATA_LOSS if reading
// fails part-way.
absl::StatusOr<std::string> ReadFile(const std::string& path);

// Replaces `path` with `text`. INTERNAL naming `path` if it cannot be
// written in full (a full disk included).
absl::Status WriteFile(const std::string& path, const std::string& text);

// A new empty directory under $TMPDIR (or /tmp) named `prefix`XXXXXX.
absl::StatusOr<std::string> MakeTempDir(const std::string& prefix);

// Removes `path` and everything below it; a missing path is OK.
absl::Status RemoveTree(const std::string& path);

// Bytes of the regular files below `directory`, but those whose path starts
// with `skip` (when set): what a directory takes, for tests and benchmarks.
// Files that vanish during the walk count as nothing.
uint64_t BytesUnder(const std::string& directory, std::string_view skip = {});

// An exclusive lock on a directory, held while the object lives (flock on
// DIRECTORY/LOCK_NAME, released by the kernel when the process ends, also
// by kill -9): one process at a time uses the directory.
class DirectoryLock {
 public:
  // FAILED_PRECONDITION naming the directory and the holder's pid (written
  // into the lock file) if another process holds it; UNAVAILABLE if the
  // file cannot be made.
  static absl::StatusOr<std::unique_ptr<DirectoryLock>> Take(
      const std::string& directory, const std::string& lock_name);
  ~DirectoryLock();
  DirectoryLock(const DirectoryLock&) = delete;
  DirectoryLock& operator=(const DirectoryLock&) = delete;

 private:
  explicit DirectoryLock(int fd) : fd_(fd) {}
  const int fd_;
};

// A temporary directory (MakeTempDir) removed with everything below it by
// the destructor, unless the environment variable FLEETMEM_KEEP_TEST_DIRS is
// set. The project's one temporary-directory helper (tests, evaluations).
class TempDir {
 public:
  // If the directory cannot be made, path() is empty and status() says why.
  explicit TempDir(const std::string& prefix = "fleetmem-");
  ~TempDir();
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;

  const std::string& path() const { return path_; }
  const absl::Status& status() const { return status_; }
  // path() + "/" + name.
  std::string Join(const std::string& name) const;

 private:
  std::string path_;
  absl::Status status_;
};

}  // namespace fleetmem::files

#endif  // FLEETMEM_SERVICES_COMMON_FILES_H_
