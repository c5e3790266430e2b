#include "services/storage/snapshot_file.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>
#include <xxhash.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <memory>
#include <optional>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "services/storage/file_io.h"

namespace fleetmem::storage {
namespace {

// FMIDXSN1 checksums every byte after the magic; FMIDXSN2 (what is
// written; FMIDXSN1 is still read) leaves out the payload's self-checked
// ranges (ByteWriter::PutSelfCheckedBytes), listed after the payload.
constexpr std::string_view kMagic = "FMIDXSN2";
constexpr std::string_view kWholeMagic = "FMIDXSN1";
// Magic and stamp before the payload; size and checksum after it.
constexpr size_t kHeaderBytes = 16;
constexpr size_t kTrailerBytes = 16;
constexpr size_t kBufferBytes = 1 << 20;

using file_io::ErrnoText;

struct HashState {
  void operator()(XXH3_state_t* state) const { XXH3_freeState(state); }
};

// Buffered writes to a file descriptor that keep the first error and a
// running checksum of everything after the magic.
class FileWriter {
 public:
  FileWriter(int fd, std::function<absl::Status()> check_room)
      : fd_(fd), check_room_(std::move(check_room)), hash_(XXH3_createState()) {
    buffer_.reserve(kBufferBytes);
    if (hash_ == nullptr || XXH3_64bits_reset(hash_.get()) != XXH_OK) {
      error_ = absl::ResourceExhaustedError("no memory for the checksum");
    }
  }
  void Append(std::span<const char> bytes, bool hashed) {
    if (hashed && hash_ != nullptr) {
      XXH3_64bits_update(hash_.get(), bytes.data(), bytes.size());
    }
    while (!bytes.empty() && error_.ok()) {
      const size_t room = kBufferBytes - buffer_.size();
      const size_t take = std::min(room, bytes.size());
      buffer_.insert(buffer_.end(), bytes.begin(), bytes.begin() + take);
      bytes = bytes.subspan(take);
      if (buffer_.size() == kBufferBytes) Flush();
    }
  }
  void Flush() {
    if (check_room_ && error_.ok() && !buffer_.empty()) {
      error_ = check_room_();
    }
    size_t done = 0;
    while (done < buffer_.size() && error_.ok()) {
      const ssize_t n =
          ::write(fd_, buffer_.data() + done, buffer_.size() - done);
      if (n < 0 && errno == EINTR) continue;
      if (n <= 0) {
        error_ = absl::UnavailableError(
            absl::StrCat("write: ", ErrnoText(n < 0 ? errno : EIO)));
        break;
      }
      done += static_cast<size_t>(n);
    }
    buffer_.clear();
  }
  uint64_t digest() const { return XXH3_64bits_digest(hash_.get()); }
  const absl::Status& error() const { return error_; }

 private:
  int fd_;
  std::function<absl::Status()> check_room_;
  std::unique_ptr<XXH3_state_t, HashState> hash_;
  std::vector<char> buffer_;
  absl::Status error_;  // the first error
};

// Appends the list of self-checked ranges and their count (checksummed).
void AppendRanges(std::span<const std::pair<uint64_t, uint64_t>> unhashed,
                  FileWriter& file) {
  for (const auto& [offset, length] : unhashed) {
    const uint64_t range[2] = {offset, length};
    file.Append({reinterpret_cast<const char*>(range), sizeof(range)}, true);
  }
  const uint64_t ranges = unhashed.size();
  file.Append({reinterpret_cast<const char*>(&ranges), sizeof(ranges)}, true);
}

// Syncs the directory that holds `path`.
absl::Status SyncParent(const std::string& path) {
  return file_io::SyncDirectory(
      std::filesystem::path(path).parent_path().string());
}

// Where a snapshot's payload starts in its file: after the header, the
// key's length and the key.
uint64_t PayloadOffset(size_t key_size) { return kHeaderBytes + 8 + key_size; }

// `fd`, closed when the last copy is dropped.
std::shared_ptr<const int> SharedDescriptor(int fd) {
  return std::shared_ptr<const int>(new int(fd), [](const int* descriptor) {
    ::close(*descriptor);
    delete descriptor;
  });
}

// A read-only mapping of a whole file, unmapped on destruction; the file
// stays open as long as its descriptor is shared.
class Mapping {
 public:
  Mapping(const char* data, size_t size, int fd)
      : data_(data), size_(size), descriptor_(SharedDescriptor(fd)) {}
  ~Mapping() {
    if (size_ > 0) ::munmap(const_cast<char*>(data_), size_);
  }
  Mapping(const Mapping&) = delete;
  Mapping& operator=(const Mapping&) = delete;
  std::span<const char> bytes() const { return {data_, size_}; }
  const std::shared_ptr<const int>& descriptor() const { return descriptor_; }

 private:
  const char* data_;
  size_t size_;
  std::shared_ptr<const int> descriptor_;
};

// Opens the snapshot at `path` for reading: NOT_FOUND when absent.
absl::StatusOr<int> OpenForReading(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd >= 0) return fd;
  const int error = errno;
  if (error == ENOENT) {
    return absl::NotFoundError(
        absl::StrCat("no index snapshot at '", path, "'"));
  }
  return absl::DataLossError(
      absl::StrCat("open '", path, "': ", ErrnoText(error)));
}

// Opens and maps the snapshot at `path`: NOT_FOUND when absent. Its pages
// are read by Populate.
absl::StatusOr<std::unique_ptr<Mapping>> Map(const std::string& path) {
  absl::StatusOr<int> opened = OpenForReading(path);
  if (!opened.ok()) return opened.status();
  const int fd = *opened;
  struct stat info;
  if (::fstat(fd, &info) != 0 ||
      static_cast<size_t>(info.st_size) < kHeaderBytes + kTrailerBytes) {
    ::close(fd);
    return absl::DataLossError(
        absl::StrCat("index snapshot '", path, "' is truncated"));
  }
  const size_t size = static_cast<size_t>(info.st_size);
  void* data = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE, fd, 0);
  const int error = errno;
  if (data == MAP_FAILED) {
    ::close(fd);
    return absl::DataLossError(
        absl::StrCat("mmap '", path, "': ", ErrnoText(error)));
  }
  ::madvise(data, size, MADV_SEQUENTIAL);
  return std::make_unique<Mapping>(static_cast<const char*>(data), size, fd);
}

// Reads `part`'s pages in at once: the checksum reads each of them anyway,
// and one pass of the kernel's read-ahead costs less than a fault per page
// (docs/performance.md, ninth round). A hint: a kernel without
// MADV_POPULATE_READ (before 5.14) faults them in as they are read.
void Populate(std::span<const char> part) {
#ifdef MADV_POPULATE_READ
  const uintptr_t page = static_cast<uintptr_t>(::sysconf(_SC_PAGESIZE));
  const uintptr_t start =
      reinterpret_cast<uintptr_t>(part.data()) / page * page;
  const uintptr_t end = reinterpret_cast<uintptr_t>(part.data()) + part.size();
  if (end > start) {
    ::madvise(reinterpret_cast<void*>(start), end - start, MADV_POPULATE_READ);
  }
#endif
}

template <typename T>
T ReadAt(std::span<const char> bytes, size_t offset) {
  T value;
  std::memcpy(&value, bytes.data() + offset, sizeof(T));
  return value;
}

// A snapshot file's frame, as its bytes say: the key's and the payload's
// sizes and the payload's self-checked ranges (offset, length; none in an
// FMIDXSN1 file).
struct Frame {
  uint64_t key_size = 0;
  uint64_t payload_size = 0;
  std::vector<std::pair<uint64_t, uint64_t>> unhashed;
};

// The frame of `bytes` (at least the header and the trailer), or nullopt
// when its magic, sizes or ranges do not fit together.
std::optional<Frame> ParseFrame(std::span<const char> bytes) {
  const std::string_view magic(bytes.data(), kMagic.size());
  const bool whole = magic == kWholeMagic;
  if (!whole && magic != kMagic) return std::nullopt;
  // Everything between the header and the trailer: the key (its length
  // first), the payload and, in FMIDXSN2, the ranges (their count last).
  uint64_t body = bytes.size() - kHeaderBytes - kTrailerBytes;
  uint64_t count = 0;
  if (!whole) {
    if (body < 8) return std::nullopt;
    count = ReadAt<uint64_t>(bytes, kHeaderBytes + body - 8);
    if (count > (body - 8) / 16) return std::nullopt;
    body -= 8 + count * 16;
  }
  // The sizes first: the trailer's payload size must fit a damaged count.
  Frame frame;
  frame.key_size = body >= 8 ? ReadAt<uint64_t>(bytes, kHeaderBytes) : 0;
  frame.payload_size = ReadAt<uint64_t>(bytes, bytes.size() - 16);
  if (body < 8 || frame.key_size > body - 8 ||
      frame.payload_size != body - 8 - frame.key_size) {
    return std::nullopt;
  }
  // In order, apart and inside the payload.
  uint64_t end = 0;
  for (uint64_t i = 0; i < count; ++i) {
    const size_t at = kHeaderBytes + body + i * 16;
    const uint64_t offset = ReadAt<uint64_t>(bytes, at);
    const uint64_t length = ReadAt<uint64_t>(bytes, at + 8);
    if (offset < end || length == 0 || offset > frame.payload_size ||
        length > frame.payload_size - offset) {
      return std::nullopt;
    }
    frame.unhashed.emplace_back(offset, length);
    end = offset + length;
  }
  return frame;
}

// What the checksum covers, in order: everything after the magic but the
// self-checked ranges and the trailer.
std::vector<std::span<const char>> HashedParts(std::span<const char> bytes,
                                               const Frame& frame) {
  std::vector<std::span<const char>> parts;
  const size_t payload = PayloadOffset(frame.key_size);
  size_t from = kMagic.size();
  for (const auto& [offset, length] : frame.unhashed) {
    parts.push_back(bytes.subspan(from, payload + offset - from));
    from = payload + offset + length;
  }
  parts.push_back(bytes.subspan(from, bytes.size() - kTrailerBytes - from));
  return parts;
}

// The checksum of `parts`; nullopt when there is no memory for its state.
std::optional<uint64_t> Digest(std::span<const std::span<const char>> parts) {
  std::unique_ptr<XXH3_state_t, HashState> state(XXH3_createState());
  if (state == nullptr || XXH3_64bits_reset(state.get()) != XXH_OK) {
    return std::nullopt;
  }
  for (const std::span<const char> part : parts) {
    XXH3_64bits_update(state.get(), part.data(), part.size());
  }
  return XXH3_64bits_digest(state.get());
}

}  // namespace

std::string SnapshotFilePath(const std::string& directory,
                             std::string_view key) {
  return absl::StrCat(
      directory, "/",
      absl::Hex(XXH3_64bits(key.data(), key.size()), absl::kZeroPad16),
      ".snapshot");
}

absl::Status WriteSnapshotFile(
    const std::string& directory, std::string_view key, uint64_t stamp,
    const std::function<absl::Status(core::ByteWriter&)>& write,
    const std::function<absl::Status()>& check_room,
    const std::function<void(uint64_t digest)>& written) {
  const std::string path = SnapshotFilePath(directory, key);
  const std::string temporary = path + ".tmp";
  std::error_code ignored;
  const int fd =
      ::open(temporary.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd < 0) {
    return absl::UnavailableError(
        absl::StrCat("no index snapshot written: open '", temporary,
                     "': ", ErrnoText(errno)));
  }
  FileWriter file(fd, check_room);
  file.Append(kMagic, /*hashed=*/false);
  file.Append({reinterpret_cast<const char*>(&stamp), sizeof(stamp)}, true);
  const uint64_t key_size = key.size();
  file.Append({reinterpret_cast<const char*>(&key_size), sizeof(key_size)},
              true);
  file.Append(key, true);
  uint64_t payload = 0;
  // The self-checked ranges (offset in the payload, length), adjacent ones
  // joined.
  std::vector<std::pair<uint64_t, uint64_t>> unhashed;
  absl::Status status;
  {
    // The payload's place in the file, for a writer's caller that reads it
    // back from there once `written` says its bytes are in (the file's
    // descriptor: the rename keeps it the snapshot's).
    const int shared = ::dup(fd);
    const core::FileBytes in_file{
        .descriptor = shared >= 0 ? SharedDescriptor(shared) : nullptr,
        .offset = PayloadOffset(key.size())};
    core::ByteWriter out(
        [&file, &payload](std::span<const char> bytes) {
          file.Append(bytes, /*hashed=*/true);
          payload += bytes.size();
        },
        shared >= 0 ? &in_file : nullptr,
        [&file, &payload, &unhashed](std::span<const char> bytes) {
          if (!unhashed.empty() &&
              unhashed.back().first + unhashed.back().second == payload) {
            unhashed.back().second += bytes.size();
          } else {
            unhashed.emplace_back(payload, bytes.size());
          }
          file.Append(bytes, /*hashed=*/false);
          payload += bytes.size();
        });
    status = write(out);
  }
  AppendRanges(unhashed, file);
  const uint64_t digest = file.digest();
  file.Append({reinterpret_cast<const char*>(&payload), sizeof(payload)},
              false);
  file.Append({reinterpret_cast<const char*>(&digest), sizeof(digest)}, false);
  file.Flush();
  if (status.ok()) status = file.error();
  if (status.ok() && written) written(digest);
  if (status.ok() && ::fsync(fd) != 0) {
    status = absl::UnavailableError(absl::StrCat("fsync: ", ErrnoText(errno)));
  }
  ::close(fd);
  if (status.ok() && ::rename(temporary.c_str(), path.c_str()) != 0) {
    status = absl::UnavailableError(absl::StrCat("rename: ", ErrnoText(errno)));
  }
  if (status.ok()) status = SyncParent(path);
  if (!status.ok()) {
    // The rename is the commit point: before it the earlier snapshot is
    // whole, after it the new one (only the directory's fsync failed).
    std::filesystem::remove(temporary, ignored);
    return absl::Status(status.code(),
                        absl::StrCat("no index snapshot written to '", path,
                                     "': ", status.message()));
  }
  return absl::OkStatus();
}

absl::Status ReadSnapshotFile(const std::string& directory,
                              std::string_view key,
                              const engine::IndexSnapshotRead& read,
                              uint64_t* stamp) {
  const std::string path = SnapshotFilePath(directory, key);
  absl::StatusOr<std::unique_ptr<Mapping>> mapping = Map(path);
  if (!mapping.ok()) {
    std::error_code ignored;
    if (absl::IsDataLoss(mapping.status())) {
      std::filesystem::remove(path, ignored);
    }
    return mapping.status();
  }
  // A damaged file is removed (the mapping stays readable after the
  // unlink): it could never be used.
  auto damaged = [&path](std::string_view what) {
    std::error_code ignored;
    std::filesystem::remove(path, ignored);
    return absl::DataLossError(
        absl::StrCat("index snapshot '", path, "' ", std::string(what)));
  };
  const std::span<const char> bytes = (*mapping)->bytes();
  const std::optional<Frame> frame = ParseFrame(bytes);
  if (!frame.has_value()) return damaged("has a damaged frame");
  const std::vector<std::span<const char>> hashed = HashedParts(bytes, *frame);
  for (const std::span<const char> part : hashed) Populate(part);
  // The checksum, once, on the thread that asks first (the reader parses
  // meanwhile: IndexSnapshotBytes).
  absl::Mutex check_mu;
  std::optional<absl::Status> verdict;
  auto check = [&]() -> absl::Status {
    absl::MutexLock lock(&check_mu);
    if (!verdict.has_value()) {
      const std::optional<uint64_t> digest = Digest(hashed);
      verdict = !digest.has_value()
                    ? absl::ResourceExhaustedError(
                          "no memory for an index snapshot's checksum")
                : *digest == ReadAt<uint64_t>(bytes, bytes.size() - 8)
                    ? absl::OkStatus()
                    : damaged("fails its checksum");
    }
    return *verdict;
  };
  const uint64_t key_size = frame->key_size;
  const uint64_t payload_size = frame->payload_size;
  if (std::string_view(bytes.data() + kHeaderBytes + 8, key_size) != key) {
    if (absl::Status checked = check(); !checked.ok()) return checked;
    return absl::NotFoundError(
        absl::StrCat("index snapshot '", path, "' belongs to another key"));
  }
  if (stamp != nullptr) *stamp = ReadAt<uint64_t>(bytes, kMagic.size());
  const core::FileBytes in_file{.descriptor = (*mapping)->descriptor(),
                                .offset = PayloadOffset(key_size)};
  const absl::Status status =
      read({.bytes = bytes.subspan(in_file.offset, payload_size),
            .file = &in_file,
            .check = check});
  if (absl::Status checked = check(); !checked.ok()) return checked;
  return status;
}

absl::StatusOr<SnapshotFileId> ReadSnapshotFileId(const std::string& directory,
                                                  std::string_view key) {
  const std::string path = SnapshotFilePath(directory, key);
  absl::StatusOr<int> opened = OpenForReading(path);
  if (!opened.ok()) return opened.status();
  const int fd = *opened;
  // The header, the key and the trailer (with an FMIDXSN2 file's count of
  // ranges before it); the payload between is not read.
  struct stat info;
  std::vector<char> head(PayloadOffset(key.size()));
  char trailer[kTrailerBytes + 8];
  const bool read =
      ::fstat(fd, &info) == 0 &&
      static_cast<size_t>(info.st_size) >= head.size() + kTrailerBytes &&
      static_cast<size_t>(info.st_size) >= sizeof(trailer) &&
      ::pread(fd, head.data(), head.size(), 0) ==
          static_cast<ssize_t>(head.size()) &&
      ::pread(fd, trailer, sizeof(trailer), info.st_size - sizeof(trailer)) ==
          static_cast<ssize_t>(sizeof(trailer));
  ::close(fd);
  const std::span<const char> header(head);
  const std::span<const char> tail(trailer, sizeof(trailer));
  const std::string_view magic(head.data(), kMagic.size());
  const uint64_t ranges = ReadAt<uint64_t>(tail, 0);
  const uint64_t after_payload = magic == kWholeMagic ? kTrailerBytes
                                 : ranges < (uint64_t{1} << 40)
                                     ? kTrailerBytes + 8 + 16 * ranges
                                     : ~uint64_t{0};
  if (!read || (magic != kMagic && magic != kWholeMagic) ||
      ReadAt<uint64_t>(header, kHeaderBytes) != key.size() ||
      std::string_view(head.data() + kHeaderBytes + 8, key.size()) != key ||
      static_cast<uint64_t>(info.st_size) < head.size() + after_payload ||
      ReadAt<uint64_t>(tail, 8) !=
          static_cast<uint64_t>(info.st_size) - head.size() - after_payload) {
    return absl::DataLossError(
        absl::StrCat("index snapshot '", path, "' has a damaged frame"));
  }
  return SnapshotFileId{.stamp = ReadAt<uint64_t>(header, kMagic.size()),
                        .digest = ReadAt<uint64_t>(tail, 16)};
}

}  // namespace fleetmem::storage
