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
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "services/storage/file_io.h"

namespace fleetmem::storage {
namespace {

constexpr std::string_view kMagic = "FMIDXSN2";
// Files of earlier builds: one checksum of the whole file, checked before
// the payload is read.
constexpr std::string_view kMagicV1 = "FMIDXSN1";
// Magic and stamp before the payload.
constexpr size_t kHeaderBytes = 16;
// After it: chunk size, payload size, checksum (V1: payload size and
// checksum).
constexpr size_t kTrailerBytes = 24;
constexpr size_t kTrailerBytesV1 = 16;
constexpr size_t kBufferBytes = 1 << 20;
// The payload is checked in chunks of this size as it is read.
constexpr uint64_t kChunkBytes = 8 << 20;
constexpr uint64_t kMostChunkBytes = uint64_t{1} << 30;

using file_io::ErrnoText;

struct HashState {
  void operator()(XXH3_state_t* state) const { XXH3_freeState(state); }
};

// Buffered writes to a file descriptor that keep the first error, a
// checksum of each chunk of the payload and a running checksum of the frame
// (stamp, key, the chunks' checksums, the chunk size).
class FileWriter {
 public:
  FileWriter(int fd, std::function<absl::Status()> check_room)
      : fd_(fd),
        check_room_(std::move(check_room)),
        frame_hash_(XXH3_createState()),
        chunk_hash_(XXH3_createState()) {
    buffer_.reserve(kBufferBytes);
    if (frame_hash_ == nullptr || chunk_hash_ == nullptr ||
        XXH3_64bits_reset(frame_hash_.get()) != XXH_OK ||
        XXH3_64bits_reset(chunk_hash_.get()) != XXH_OK) {
      error_ = absl::ResourceExhaustedError("no memory for the checksum");
    }
  }
  // Bytes outside every checksum (the magic, the payload's size, the
  // checksum itself).
  void Append(std::span<const char> bytes) {
    while (!bytes.empty() && error_.ok()) {
      const size_t room = kBufferBytes - buffer_.size();
      const size_t take = std::min(room, bytes.size());
      buffer_.insert(buffer_.end(), bytes.begin(), bytes.begin() + take);
      bytes = bytes.subspan(take);
      if (buffer_.size() == kBufferBytes) Flush();
    }
  }
  // Bytes of the frame's checksum.
  void AppendFramed(std::span<const char> bytes) {
    if (error_.ok())
      XXH3_64bits_update(frame_hash_.get(), bytes.data(), bytes.size());
    Append(bytes);
  }
  template <typename T>
  void AppendFramedValue(const T& value) {
    AppendFramed({reinterpret_cast<const char*>(&value), sizeof(value)});
  }
  // Payload bytes, checksummed a chunk at a time.
  void AppendPayload(std::span<const char> bytes) {
    Append(bytes);
    while (!bytes.empty() && error_.ok()) {
      const size_t take =
          std::min<uint64_t>(bytes.size(), kChunkBytes - in_chunk_);
      XXH3_64bits_update(chunk_hash_.get(), bytes.data(), take);
      in_chunk_ += take;
      payload_ += take;
      bytes = bytes.subspan(take);
      if (in_chunk_ == kChunkBytes) EndChunk();
    }
  }
  // Writes the chunks' checksums and the chunk size (both framed), the
  // payload's size and the frame's checksum.
  void AppendTrailer() {
    if (in_chunk_ > 0) EndChunk();
    for (uint64_t digest : chunk_digests_) AppendFramedValue(digest);
    AppendFramedValue(kChunkBytes);
    const uint64_t payload = payload_;
    Append({reinterpret_cast<const char*>(&payload), sizeof(payload)});
    const uint64_t digest =
        error_.ok() ? XXH3_64bits_digest(frame_hash_.get()) : 0;
    Append({reinterpret_cast<const char*>(&digest), sizeof(digest)});
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
  const absl::Status& error() const { return error_; }

 private:
  void EndChunk() {
    chunk_digests_.push_back(XXH3_64bits_digest(chunk_hash_.get()));
    XXH3_64bits_reset(chunk_hash_.get());
    in_chunk_ = 0;
  }

  int fd_;
  std::function<absl::Status()> check_room_;
  std::unique_ptr<XXH3_state_t, HashState> frame_hash_;
  std::unique_ptr<XXH3_state_t, HashState> chunk_hash_;
  uint64_t in_chunk_ = 0;
  uint64_t payload_ = 0;
  std::vector<uint64_t> chunk_digests_;
  std::vector<char> buffer_;
  absl::Status error_;  // the first error
};

// Checks a payload's chunks against their checksums as a reader reaches
// them (core::ByteVerifier).
class ChunkVerifier : public core::ByteVerifier {
 public:
  ChunkVerifier(std::span<const char> payload, const char* digests,
                uint64_t chunk_bytes)
      : payload_(payload), digests_(digests), chunk_bytes_(chunk_bytes) {}

  size_t VerifyTo(size_t end) override {
    while (verified_ < end && !failed_) {
      const size_t size =
          std::min<uint64_t>(chunk_bytes_, payload_.size() - verified_);
      uint64_t expected = 0;
      std::memcpy(&expected, digests_ + verified_ / chunk_bytes_ * 8, 8);
      if (XXH3_64bits(payload_.data() + verified_, size) != expected) {
        failed_ = true;
        failed_chunk_ = verified_ / chunk_bytes_;
        break;
      }
      verified_ += size;
      Prefetch();
    }
    return failed_ ? 0 : verified_;
  }
  bool failed() const { return failed_; }
  uint64_t failed_chunk() const { return failed_chunk_; }
  uint64_t chunks() const {
    return (payload_.size() + chunk_bytes_ - 1) / chunk_bytes_;
  }

 private:
  // Asks the kernel to read the next chunks of the mapping while the
  // reader works on this one (its own readahead is a few hundred KiB; a
  // load that reads a chunk, then computes, then reads the next left the
  // disk idle meanwhile).
  void Prefetch() {
    const size_t ahead = std::min<uint64_t>(
        payload_.size(), verified_ + kPrefetchChunks * chunk_bytes_);
    if (ahead <= prefetched_ || ahead <= verified_) return;
    const size_t from = std::max(prefetched_, verified_);
    const uintptr_t page = static_cast<uintptr_t>(::sysconf(_SC_PAGESIZE));
    const uintptr_t start =
        reinterpret_cast<uintptr_t>(payload_.data() + from) & ~(page - 1);
    const uintptr_t end = reinterpret_cast<uintptr_t>(payload_.data() + ahead);
    ::madvise(reinterpret_cast<void*>(start), end - start, MADV_WILLNEED);
    prefetched_ = ahead;
  }

  static constexpr uint64_t kPrefetchChunks = 4;
  std::span<const char> payload_;
  const char* digests_;
  uint64_t chunk_bytes_;
  size_t verified_ = 0;
  bool failed_ = false;
  uint64_t failed_chunk_ = 0;
  size_t prefetched_ = 0;
};

// Syncs the directory that holds `path`.
absl::Status SyncParent(const std::string& path) {
  return file_io::SyncDirectory(
      std::filesystem::path(path).parent_path().string());
}

// A read-only mapping of a whole file, unmapped on destruction.
class Mapping {
 public:
  Mapping(const char* data, size_t size) : data_(data), size_(size) {}
  ~Mapping() {
    if (size_ > 0) ::munmap(const_cast<char*>(data_), size_);
  }
  Mapping(const Mapping&) = delete;
  Mapping& operator=(const Mapping&) = delete;
  std::span<const char> bytes() const { return {data_, size_}; }

 private:
  const char* data_;
  size_t size_;
};

// Opens and maps the snapshot at `path`: NOT_FOUND when absent.
absl::StatusOr<std::unique_ptr<Mapping>> Map(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    const int error = errno;
    if (error == ENOENT) {
      return absl::NotFoundError(
          absl::StrCat("no index snapshot at '", path, "'"));
    }
    return absl::DataLossError(
        absl::StrCat("open '", path, "': ", ErrnoText(error)));
  }
  struct stat info;
  if (::fstat(fd, &info) != 0 ||
      static_cast<size_t>(info.st_size) < kHeaderBytes + kTrailerBytesV1) {
    ::close(fd);
    return absl::DataLossError(
        absl::StrCat("index snapshot '", path, "' is truncated"));
  }
  const size_t size = static_cast<size_t>(info.st_size);
  void* data = ::mmap(nullptr, size, PROT_READ, MAP_PRIVATE, fd, 0);
  const int error = errno;
  ::close(fd);
  if (data == MAP_FAILED) {
    return absl::DataLossError(
        absl::StrCat("mmap '", path, "': ", ErrnoText(error)));
  }
  ::madvise(data, size, MADV_SEQUENTIAL);
  return std::make_unique<Mapping>(static_cast<const char*>(data), size);
}

template <typename T>
T ReadAt(std::span<const char> bytes, size_t offset) {
  T value;
  std::memcpy(&value, bytes.data() + offset, sizeof(T));
  return value;
}

// NOT_FOUND unless the file's key (after the header and its size) is
// `key`; then `*stamp`, if given, gets the file's stamp.
absl::Status CheckKey(std::span<const char> bytes, uint64_t key_size,
                      std::string_view key, const std::string& path,
                      uint64_t* stamp) {
  if (std::string_view(bytes.data() + kHeaderBytes + 8, key_size) != key) {
    return absl::NotFoundError(
        absl::StrCat("index snapshot '", path, "' belongs to another key"));
  }
  if (stamp != nullptr) *stamp = ReadAt<uint64_t>(bytes, kMagic.size());
  return absl::OkStatus();
}

// A file of the first format: its one checksum is checked over the whole
// file before `read` sees the payload.
absl::Status ReadWholeFileChecked(
    std::span<const char> bytes, std::string_view key, const std::string& path,
    const std::function<absl::Status(core::ByteReader&)>& read, uint64_t* stamp,
    const std::function<absl::Status(std::string_view)>& damaged) {
  // Everything between the header and the trailer: the key, then the
  // payload.
  const size_t body_size = bytes.size() - kHeaderBytes - kTrailerBytesV1;
  const uint64_t payload_size = ReadAt<uint64_t>(bytes, bytes.size() - 16);
  const uint64_t key_size =
      body_size >= 8 ? ReadAt<uint64_t>(bytes, kHeaderBytes) : 0;
  if (body_size < 8 || key_size > body_size - 8 ||
      payload_size != body_size - 8 - key_size) {
    return damaged("has a damaged frame");
  }
  const uint64_t digest =
      XXH3_64bits(bytes.data() + kMagic.size(), 8 + body_size);
  if (digest != ReadAt<uint64_t>(bytes, bytes.size() - 8)) {
    return damaged("fails its checksum");
  }
  if (absl::Status status = CheckKey(bytes, key_size, key, path, stamp);
      !status.ok()) {
    return status;
  }
  core::ByteReader in(bytes.subspan(kHeaderBytes + 8 + key_size, payload_size));
  return read(in);
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
    const std::function<void()>& written) {
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
  file.Append(kMagic);
  file.AppendFramedValue(stamp);
  file.AppendFramedValue(static_cast<uint64_t>(key.size()));
  file.AppendFramed(key);
  absl::Status status;
  {
    core::ByteWriter out(
        [&file](std::span<const char> bytes) { file.AppendPayload(bytes); });
    status = write(out);
  }
  file.AppendTrailer();
  file.Flush();
  if (status.ok()) status = file.error();
  if (status.ok() && written) written();
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

absl::Status ReadSnapshotFile(
    const std::string& directory, std::string_view key,
    const std::function<absl::Status(core::ByteReader&)>& read,
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
  const std::string_view magic(bytes.data(), kMagic.size());
  if (magic == kMagicV1) {
    return ReadWholeFileChecked(bytes, key, path, read, stamp, damaged);
  }
  if (magic != kMagic || bytes.size() < kHeaderBytes + 8 + kTrailerBytes) {
    return damaged("has a damaged frame");
  }
  // header | key size, key | payload | chunk checksums | chunk size |
  // payload size | frame checksum.
  const uint64_t key_size = ReadAt<uint64_t>(bytes, kHeaderBytes);
  const uint64_t chunk_bytes = ReadAt<uint64_t>(bytes, bytes.size() - 24);
  const uint64_t payload_size = ReadAt<uint64_t>(bytes, bytes.size() - 16);
  const uint64_t room = bytes.size() - kHeaderBytes - 8 - kTrailerBytes;
  if (chunk_bytes == 0 || chunk_bytes > kMostChunkBytes || key_size > room ||
      payload_size > room - key_size) {
    return damaged("has a damaged frame");
  }
  const uint64_t chunks = (payload_size + chunk_bytes - 1) / chunk_bytes;
  if (chunks > (room - key_size - payload_size) / 8 ||
      chunks * 8 != room - key_size - payload_size) {
    return damaged("has a damaged frame");
  }
  // The frame's checksum covers the stamp, the key and the chunks'
  // checksums: the payload is then checked a chunk at a time as it is read.
  const size_t digests_at = kHeaderBytes + 8 + key_size + payload_size;
  std::unique_ptr<XXH3_state_t, HashState> frame(XXH3_createState());
  if (frame == nullptr || XXH3_64bits_reset(frame.get()) != XXH_OK) {
    return absl::ResourceExhaustedError("no memory for the checksum");
  }
  XXH3_64bits_update(frame.get(), bytes.data() + kMagic.size(), 16 + key_size);
  XXH3_64bits_update(frame.get(), bytes.data() + digests_at, chunks * 8 + 8);
  const uint64_t frame_digest = XXH3_64bits_digest(frame.get());
  if (frame_digest != ReadAt<uint64_t>(bytes, bytes.size() - 8)) {
    return damaged("fails its checksum");
  }
  if (absl::Status status = CheckKey(bytes, key_size, key, path, stamp);
      !status.ok()) {
    return status;
  }
  const std::span<const char> payload =
      bytes.subspan(kHeaderBytes + 8 + key_size, payload_size);
  ChunkVerifier verifier(payload, bytes.data() + digests_at, chunk_bytes);
  core::ByteReader in(payload, &verifier);
  absl::Status status = read(in);
  // What the reader did not reach must hold too: a damaged file is never
  // reported as read.
  if (!verifier.failed()) verifier.VerifyTo(payload.size());
  if (verifier.failed()) {
    return damaged(absl::StrCat("fails its checksum (chunk ",
                                verifier.failed_chunk() + 1, " of ",
                                verifier.chunks(), ")"));
  }
  return status;
}

}  // namespace fleetmem::storage
