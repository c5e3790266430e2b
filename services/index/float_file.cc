#include "services/index/float_file.h"

#include <fcntl.h>
#include <stdlib.h>
#include <sys/stat.h>
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

void FileFloatRows::Open() {
  if (fd_ >= 0) return;
  std::string path = absl::StrCat(directory_, "/graph-floats-XXXXXX");
  const int fd = ::mkostemp(path.data(), O_CLOEXEC);
  if (fd < 0) Fail(errno, absl::StrCat("making a file in ", directory_));
  ::unlink(path.c_str());  // the open descriptor keeps it
  fd_ = fd;
}

void FileFloatRows::Reserve(size_t rows) {
  if (rows <= reserved_) return;
  Open();
  const size_t target =
      std::max({rows, reserved_ + reserved_ / 4, static_cast<size_t>(1024)});
  const size_t row_bytes = width() * sizeof(float);
  // The adopted rows' blocks are the adopted file's (a hole here).
  const size_t from = std::min(adopted_, target) * row_bytes;
  const int error =
      ::posix_fallocate(fd_, static_cast<off_t>(from),
                        static_cast<off_t>(target * row_bytes - from));
  if (error != 0) {
    Fail(error, absl::StrCat("allocating ", target * row_bytes,
                             " bytes for the graph's floats in ", directory_));
  }
  reserved_ = target;
}

void FileFloatRows::Write(size_t first, size_t count, const float* values) {
  Open();
  const size_t row_bytes = width() * sizeof(float);
  TransferAll(
      reinterpret_cast<const char*>(values), count * row_bytes,
      static_cast<off_t>(first * row_bytes),
      [this](const char* data, size_t bytes, off_t offset) {
        return ::pwrite(fd_, data, bytes, offset);
      },
      "writing the graph's floats");
  // Read from here from now on (after the write: a failed one leaves the
  // adopted row).
  for (size_t row = first; row < std::min(first + count, adopted_); ++row) {
    rewritten_[row / 64].fetch_or(uint64_t{1} << (row % 64),
                                  std::memory_order_release);
  }
}

FileFloatRows::Place FileFloatRows::PlaceOf(size_t row) const {
  const size_t row_bytes = width() * sizeof(float);
  if (row < adopted_ && (rewritten_[row / 64].load(std::memory_order_acquire) &
                         (uint64_t{1} << (row % 64))) == 0) {
    return {*adopted_file_.descriptor,
            static_cast<off_t>(adopted_offset_ + row * row_bytes)};
  }
  return {fd_, static_cast<off_t>(row * row_bytes)};
}

void FileFloatRows::Check(size_t row, const Place& place,
                          const float* values) const {
  if (checks_.empty() || place.fd == fd_) return;  // one per adopted row
  if (core::RowCheck({values, width()}) == checks_[row]) return;
  Fail(static_cast<int>(std::errc::bad_message),
       absl::StrCat("row ", row,
                    " of the graph's floats fails its checksum in the index "
                    "snapshot's file (byte ",
                    place.offset, ")"));
}

void FileFloatRows::Read(size_t first, size_t count, float* values) const {
  const size_t row_bytes = width() * sizeof(float);
  // Runs of rows in one file, each read at once.
  for (size_t row = first; row < first + count;) {
    const Place place = PlaceOf(row);
    size_t run = 1;
    while (row + run < first + count) {
      const Place next = PlaceOf(row + run);
      if (next.fd != place.fd ||
          next.offset != place.offset + static_cast<off_t>(run * row_bytes)) {
        break;
      }
      ++run;
    }
    float* out = values + (row - first) * width();
    TransferAll(
        reinterpret_cast<char*>(out), run * row_bytes, place.offset,
        [fd = place.fd](char* data, size_t bytes, off_t offset) {
          return ::pread(fd, data, bytes, offset);
        },
        "reading the graph's floats");
    for (size_t k = 0; k < run; ++k) {
      Check(row + k,
            {place.fd, place.offset + static_cast<off_t>(k * row_bytes)},
            out + k * width());
    }
    row += run;
  }
}

bool FileFloatRows::Adopt(const core::FileBytes& file, uint64_t offset,
                          size_t rows, std::span<const uint32_t> keep,
                          std::span<const uint32_t> checks) {
  if (file.descriptor == nullptr || (!checks.empty() && checks.size() < rows)) {
    return false;
  }
  const size_t row_bytes = width() * sizeof(float);
  const size_t words = (rows + 63) / 64;
  auto rewritten = std::make_unique<std::atomic<uint64_t>[]>(words);
  for (size_t word = 0; word < words; ++word) rewritten[word] = 0;
  for (const uint32_t row : keep) {
    rewritten[row / 64].fetch_or(uint64_t{1} << (row % 64));
  }
  if (fd_ >= 0) {
    // The rows' copies here are not read again: their blocks go back (a
    // hint; where the file system cannot punch, they only cost disk), each
    // run between two kept rows at once.
    size_t from = 0;
    auto punch = [&](size_t end) {
      if (end > from) {
        ::fallocate(fd_, FALLOC_FL_PUNCH_HOLE | FALLOC_FL_KEEP_SIZE,
                    static_cast<off_t>(from * row_bytes),
                    static_cast<off_t>((end - from) * row_bytes));
      }
    };
    for (const uint32_t row : keep) {
      punch(row);
      from = static_cast<size_t>(row) + 1;
    }
    punch(rows);
  }
  adopted_file_ = file;
  adopted_offset_ = offset;
  adopted_ = rows;
  rewritten_ = std::move(rewritten);
  // A copy of the rows' checks alone (4 bytes a row).
  checks_.assign(checks.begin(), checks.begin() + (checks.empty() ? 0 : rows));
  reserved_ = std::max(reserved_, rows);
  return true;
}

size_t FileFloatRows::AllocatedBytes() const {
  struct stat info;
  if (fd_ < 0 || ::fstat(fd_, &info) != 0) return 0;
  return static_cast<size_t>(info.st_blocks) * 512;
}

void FileFloatRows::Gather(std::span<const uint32_t> rows,
                           float* values) const {
  if (!nowait_.load(std::memory_order_relaxed)) {
    core::FloatRows::Gather(rows, values);
    return;
  }
  const size_t row_bytes = width() * sizeof(float);
  std::vector<size_t> missed;  // of rows: not whole in the page cache
  for (size_t i = 0; i < rows.size(); ++i) {
    iovec target{values + i * width(), row_bytes};
    const Place place = PlaceOf(rows[i]);
    ssize_t copied;
    do {
      copied = ::preadv2(place.fd, &target, 1, place.offset, RWF_NOWAIT);
    } while (copied < 0 && errno == EINTR);
    if (copied == static_cast<ssize_t>(row_bytes)) {
      Check(rows[i], place, values + i * width());
      continue;
    }
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
    const Place place = PlaceOf(rows[i]);
    ::posix_fadvise(place.fd, place.offset, static_cast<off_t>(row_bytes),
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
