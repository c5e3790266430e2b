#include "tests/small_filesystem.h"

#include <sys/mount.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <fstream>

#include "absl/strings/str_cat.h"

namespace fleetmem::testing {

SmallFilesystem::SmallFilesystem(const std::string& path, int size_mib)
    : path_(path) {
  if (geteuid() != 0) {
    why_not_ = "not root: cannot mount a tmpfs";
    return;
  }
  const std::string options = absl::StrCat("size=", size_mib, "m");
  if (mount("tmpfs", path.c_str(), "tmpfs", 0, options.c_str()) != 0) {
    why_not_ = absl::StrCat("mount tmpfs on ", path, ": ", strerror(errno));
    return;
  }
  mounted_ = true;
}

SmallFilesystem::~SmallFilesystem() {
  if (mounted_) umount2(path_.c_str(), MNT_DETACH);
}

uint64_t FreeBytes(const std::string& path) {
  struct statvfs info;
  if (statvfs(path.c_str(), &info) != 0) return 0;
  return static_cast<uint64_t>(info.f_bavail) * info.f_frsize;
}

void Fill(const std::string& file, uint64_t bytes) {
  std::ofstream out(file, std::ios::binary);
  const std::string chunk(kMiB, '\0');
  for (uint64_t written = 0; written < bytes; written += chunk.size()) {
    out.write(chunk.data(), static_cast<std::streamsize>(std::min<uint64_t>(
                                chunk.size(), bytes - written)));
  }
}

}  // namespace fleetmem::testing
