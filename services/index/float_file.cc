#include "services/index/float_file.h"

#include <fcntl.h>
#include <stdlib.h>
#include <sys/uio.h>
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

// Moves `bytes` between `data` and the file at `offset` with `io` (pread
// or pwrite), going on after a partial transfer or an interruption.
template <typename Byte, typename Io>
void TransferAll(Byte* data, size_t bytes, off_t offset, Io io,
                 const char* what) {
  while (bytes > 0) {
    const ssize_t moved = io(data, bytes, offset);
    if (moved < 0 && errno == EINTR) continue;
    if (moved < 0) Fail(errno, what);
    if (moved == 0) Fail(EIO, absl::StrCat(what, ": past the file's end"));
    data += moved;
    offset += moved;
    bytes -= static_cast<size_t>(moved);
  }
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
  TransferAll(
      reinterpret_cast<const char*>(values), count * row_bytes,
      static_cast<off_t>(first * row_bytes),
      [this](const char* data, size_t bytes, off_t offset) {
        return ::pwrite(fd_, data, bytes, offset);
      },
      "writing the graph's floats");
}

void FileFloatRows::Read(size_t first, size_t count, float* values) const {
  const size_t row_bytes = width() * sizeof(float);
  TransferAll(
      reinterpret_cast<char*>(values), count * row_bytes,
      static_cast<off_t>(first * row_bytes),
      [this](char* data, size_t bytes, off_t offset) {
        return ::pread(fd_, data, bytes, offset);
      },
      "reading the graph's floats");
}

void FileFloatRows::Gather(std::span<const uint32_t> rows,
                           float* values) const {
  if (!nowait_.load(std::memory_order_relaxed)) {
    core::FloatRows::Gather(rows, values);
    return;
  }
  const size_t row_bytes = width() * sizeof(float);
  auto offset = [&](uint32_t row) {
    return static_cast<off_t>(static_cast<size_t>(row) * row_bytes);
  };
  std::vector<size_t> missed;  // of rows: not whole in the page cache
  for (size_t i = 0; i < rows.size(); ++i) {
    iovec target{values + i * width(), row_bytes};
    ssize_t copied;
    do {
      copied = ::preadv2(fd_, &target, 1, offset(rows[i]), RWF_NOWAIT);
    } while (copied < 0 && errno == EINTR);
    if (copied == static_cast<ssize_t>(row_bytes)) continue;
    if (copied < 0 && errno != EAGAIN) {
      if (errno != EOPNOTSUPP && errno != EINVAL && errno != ENOSYS) {
        Fail(errno, "reading the graph's floats");
      }
      nowait_.store(false, std::memory_order_relaxed);
    }
    missed.push_back(i);
  }
  // A hint: where it fails, the reads below wait for each row in turn.
  for (const size_t i : missed) {
    ::posix_fadvise(fd_, offset(rows[i]), static_cast<off_t>(row_bytes),
                    POSIX_FADV_WILLNEED);
  }
  for (const size_t i : missed) Read(rows[i], 1, values + i * width());
}

core::FloatRowsMaker FloatRowsInFiles(std::string directory) {
  return [directory = std::move(directory)](size_t width) {
    return std::make_unique<FileFloatRows>(directory, width);
  };
}

}  // namespace fleetmem::index
