// Plain binary encoding for snapshots of in-memory structures (an index's
// graph, the engine's handle table): fixed-width values in the machine's byte
// order and runs of bytes. No I/O: a ByteWriter hands its bytes to a sink
// function, a ByteReader reads from bytes it is given. The snapshots are
// caches written and read by the same build on the same machine (a format
// version guards them), not an exchange format.
#ifndef FLEETMEM_SERVICES_CORE_BYTE_STREAM_H_
#define FLEETMEM_SERVICES_CORE_BYTE_STREAM_H_

#include <cstddef>
#include <cstdint>
#include <cstring>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>

namespace fleetmem::core {

// Where a ByteReader's or a ByteWriter's bytes lie in a file, when they do
// (an index snapshot, which services/storage maps to read and writes
// through a sink): a reader keeping a large part of its bytes, or a writer's
// caller whose memory holds what it wrote, may read that part from the
// file later instead of keeping a copy. Such a file is never changed once
// written (a newer one replaces it by a rename, which leaves this one
// readable through `descriptor`). The core reads no file: it only passes
// this along (FloatRows::Adopt).
struct FileBytes {
  // The open file; closed when the last copy is dropped.
  std::shared_ptr<const int> descriptor;
  // Where in the file the stream's first byte is.
  uint64_t offset = 0;
};

// Receives bytes in order. The sink's owner records its own errors (a full
// disk) and reports them once the writing is done.
using ByteSink = std::function<void(std::span<const char>)>;

class ByteWriter {
 public:
  // `self_checked`, if given, receives what PutSelfCheckedBytes writes
  // (else `sink` does): a sink that checksums its bytes (an index
  // snapshot's file) may leave those out.
  explicit ByteWriter(ByteSink sink, const FileBytes* file = nullptr,
                      ByteSink self_checked = nullptr)
      : sink_(std::move(sink)),
        self_checked_(std::move(self_checked)),
        file_(file) {}

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
  // Bytes whose integrity the payload checks itself, part by part (an int8
  // graph's floats, each row's checksum written after them): a reader can
  // trust the rest without reading these, and checks a part when it reads
  // it. Lie in the stream like PutBytes's.
  void PutSelfCheckedBytes(const void* data, size_t size) {
    if (size == 0) return;
    (self_checked_ ? self_checked_ : sink_)(
        std::span<const char>(static_cast<const char*>(data), size));
    written_ += size;
  }
  // Length (uint64) then the characters.
  void PutString(std::string_view text) {
    Put<uint64_t>(text.size());
    PutBytes(text.data(), text.size());
  }
  uint64_t written() const { return written_; }
  // The file the sink writes to, its first byte written() == 0's (nullptr:
  // none, or not said). Its bytes are in the file once the sink's owner
  // says so (a snapshot's `written`), not when Put returns.
  const FileBytes* file() const { return file_; }

 private:
  ByteSink sink_;
  ByteSink self_checked_;
  const FileBytes* file_;
  uint64_t written_ = 0;
};

// Reads what a ByteWriter wrote. Every Get returns false, and reads nothing,
// when fewer bytes remain than it needs; callers turn that into DATA_LOSS.
class ByteReader {
 public:
  // `file`, if given, holds `bytes` from its offset on and outlives the
  // reader.
  explicit ByteReader(std::span<const char> bytes,
                      const FileBytes* file = nullptr)
      : bytes_(bytes), file_(file) {}

  template <typename T>
  bool Get(T* value) {
    static_assert(std::is_trivially_copyable_v<T>);
    return GetBytes(value, sizeof(T));
  }
  bool GetBytes(void* out, size_t size) {
    if (size > remaining()) return false;
    if (size > 0) std::memcpy(out, bytes_.data() + position_, size);
    position_ += size;
    return true;
  }
  // At most `max_size` characters (a corrupt length must not allocate).
  bool GetString(std::string* text, size_t max_size) {
    uint64_t size = 0;
    if (!Get(&size) || size > max_size || size > remaining()) return false;
    text->assign(bytes_.data() + position_, size);
    position_ += size;
    return true;
  }
  // The next `size` bytes as they are (no copy), skipped over.
  bool GetSpan(size_t size, std::span<const char>* out) {
    if (size > remaining()) return false;
    *out = bytes_.subspan(position_, size);
    position_ += size;
    return true;
  }
  size_t remaining() const { return bytes_.size() - position_; }
  // The file the bytes lie in (nullptr: none), and where in it a span
  // GetSpan returned starts.
  const FileBytes* file() const { return file_; }
  uint64_t FileOffset(std::span<const char> part) const {
    return file_->offset + static_cast<uint64_t>(part.data() - bytes_.data());
  }

 private:
  std::span<const char> bytes_;
  const FileBytes* file_;
  size_t position_ = 0;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_BYTE_STREAM_H_
