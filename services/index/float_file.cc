#include "services/index/float_file.h"

#include <fcntl.h>
#include <stdlib.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <memory>
#include <string>
#include <system_error>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"

namespace fleetmem::index {
namespace {

[[noreturn]] void Fail(int error, const std::string& what) {
  throw std::system_error(error, std::generic_category(), what);
}

}  // namespace

FileFloatRows::FileFloatRows(std::string directory, size_t width)
    : core::FloatRows(width), directory_(std::move(directory)) {}

FileFloatRows::~FileFloatRows() {
  if (fd_ >= 0) ::close(fd_);
}

void FileFloatRows::Reserve(size_t rows) {
  if (rows <= reserved_) return;
  if (fd_ < 0) {
    std::string path = absl::StrCat(directory_, "/graph-floats-XXXXXX");
    const int fd = ::mkostemp(path.data(), O_CLOEXEC);
    if (fd < 0) Fail(errno, absl::StrCat("making a file in ", directory_));
    ::unlink(path.c_str());  // the open descriptor keeps it
    fd_ = fd;
  }
  const size_t target =
      std::max({rows, reserved_ + reserved_ / 4, static_cast<size_t>(1024)});
  const size_t row_bytes = width() * sizeof(float);
  const int error = ::posix_fallocate(fd_, 0, target * row_bytes);
  if (error != 0) {
    Fail(error, absl::StrCat("allocating ", target * row_bytes,
                             " bytes for the graph's floats in ", directory_));
  }
  reserved_ = target;
}

void FileFloatRows::Write(size_t first, size_t count, const float* values) {
  const size_t row_bytes = width() * sizeof(float);
  const char* data = reinterpret_cast<const char*>(values);
  size_t left = count * row_bytes;
  off_t offset = static_cast<off_t>(first * row_bytes);
  while (left > 0) {
    const ssize_t written = ::pwrite(fd_, data, left, offset);
    if (written < 0) {
      if (errno == EINTR) continue;
      Fail(errno, "writing the graph's floats");
    }
    data += written;
    offset += written;
    left -= static_cast<size_t>(written);
  }
}

void FileFloatRows::Read(size_t first, size_t count, float* values) const {
  const size_t row_bytes = width() * sizeof(float);
  char* data = reinterpret_cast<char*>(values);
  size_t left = count * row_bytes;
  off_t offset = static_cast<off_t>(first * row_bytes);
  while (left > 0) {
    const ssize_t got = ::pread(fd_, data, left, offset);
    if (got < 0) {
      if (errno == EINTR) continue;
      Fail(errno, "reading the graph's floats");
    }
    if (got == 0) Fail(EIO, "reading the graph's floats: past the file's end");
    data += got;
    offset += got;
    left -= static_cast<size_t>(got);
  }
}

core::FloatRowsMaker FloatRowsInFiles(std::string directory) {
  return [directory = std::move(directory)](size_t width) {
    return std::make_unique<FileFloatRows>(directory, width);
  };
}

}  // namespace fleetmem::index
