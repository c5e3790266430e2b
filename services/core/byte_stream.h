// Plain binary encoding for snapshots of in-memory structures (an index's
// graph, the engine's handle table): fixed-width values in the machine's byte
// order and runs of bytes. No I/O: a ByteWriter hands its bytes to a sink
// function, a ByteReader reads from bytes it is given. The snapshots are
// caches written and read by the same build on the same machine (a format
// version guards them), not an exchange format.
#ifndef FLEETMEM_SERVICES_CORE_BYTE_STREAM_H_
#define FLEETMEM_SERVICES_CORE_BYTE_STREAM_H_

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>

namespace fleetmem::core {

// Receives bytes in order. The sink's owner records its own errors (a full
// disk) and reports them once the writing is done.
using ByteSink = std::function<void(std::span<const char>)>;

class ByteWriter {
 public:
  explicit ByteWriter(ByteSink sink) : sink_(std::move(sink)) {}

  template <typename T>
  void Put(const T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    PutBytes(&value, sizeof(T));
  }
  void PutBytes(const void* data, size_t size) {
    if (size == 0) return;
    sink_(std::span<const char>(static_cast<const char*>(data), size));
    written_ += size;
  }
  // Length (uint64) then the characters.
  void PutString(std::string_view text) {
    Put<uint64_t>(text.size());
    PutBytes(text.data(), text.size());
  }
  uint64_t written() const { return written_; }

 private:
  ByteSink sink_;
  uint64_t written_ = 0;
};

// Checks bytes before a ByteReader hands them out: a file verified a chunk
// at a time as it is read (storage's index snapshots), so that a reader
// never sees a byte that failed its checksum, and the file is read once.
class ByteVerifier {
 public:
  virtual ~ByteVerifier() = default;
  // Verifies the bytes up to at least `end` (<= the reader's size) and
  // returns how far they are verified now (>= end), or 0 when they fail.
  virtual size_t VerifyTo(size_t end) = 0;
};

// Reads what a ByteWriter wrote. Every Get returns false, and reads nothing,
// when fewer bytes remain than it needs; callers turn that into DATA_LOSS.
// With a verifier, a Get also returns false when the bytes it would read
// fail their check (what was read before stays read); a large GetBytes
// verifies and copies a chunk at a time.
class ByteReader {
 public:
  explicit ByteReader(std::span<const char> bytes,
                      ByteVerifier* verifier = nullptr)
      : bytes_(bytes),
        verifier_(verifier),
        verified_(verifier == nullptr ? bytes.size() : 0) {}

  template <typename T>
  bool Get(T* value) {
    static_assert(std::is_trivially_copyable_v<T>);
    return GetBytes(value, sizeof(T));
  }
  bool GetBytes(void* out, size_t size) {
    if (size > remaining()) return false;
    char* to = static_cast<char*>(out);
    while (size > 0) {
      if (position_ == verified_ && !Verify(position_ + 1)) return false;
      const size_t take = std::min(size, verified_ - position_);
      std::memcpy(to, bytes_.data() + position_, take);
      position_ += take;
      to += take;
      size -= take;
    }
    return true;
  }
  // At most `max_size` characters (a corrupt length must not allocate).
  bool GetString(std::string* text, size_t max_size) {
    uint64_t size = 0;
    if (!Get(&size) || size > max_size || size > remaining() ||
        !Verify(position_ + size)) {
      return false;
    }
    text->assign(bytes_.data() + position_, size);
    position_ += size;
    return true;
  }
  // The next `size` bytes as they are (no copy), skipped over.
  bool GetSpan(size_t size, std::span<const char>* out) {
    if (size > remaining() || !Verify(position_ + size)) return false;
    *out = bytes_.subspan(position_, size);
    position_ += size;
    return true;
  }
  size_t remaining() const { return bytes_.size() - position_; }

 private:
  // True once the bytes up to `end` are verified.
  bool Verify(size_t end) {
    if (end <= verified_) return true;
    const size_t verified = verifier_->VerifyTo(end);
    if (verified < end) return false;
    verified_ = verified;
    return true;
  }

  std::span<const char> bytes_;
  size_t position_ = 0;
  ByteVerifier* verifier_;
  size_t verified_;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_BYTE_STREAM_H_
