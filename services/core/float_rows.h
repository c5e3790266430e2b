// Rows of floats of one width under dense row numbers: where an int8
// HnswGraph keeps each code as given (and its scale) beside its quantized
// nodes, for rescoring and for the caller's copies. The graph reads a row
// only to rescore a search's candidates and to copy a code out, never while
// it walks or links, so the rows need not be in the process's memory:
// MemoryFloatRows keeps them in blocks on the heap; services/index's
// FileFloatRows in a file the page cache holds (pread/pwrite).
// Not thread-safe for writers; Read may run beside Write of another row
// (the graph's Link calls beside rescoring searches).
#ifndef FLEETMEM_SERVICES_CORE_FLOAT_ROWS_H_
#define FLEETMEM_SERVICES_CORE_FLOAT_ROWS_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <vector>

#include "services/core/byte_stream.h"

namespace fleetmem::core {

class FloatRows {
 public:
  explicit FloatRows(size_t width) : width_(width) {}
  virtual ~FloatRows() = default;
  FloatRows(const FloatRows&) = delete;
  FloatRows& operator=(const FloatRows&) = delete;

  // Floats per row.
  size_t width() const { return width_; }
  // Room for rows [0, rows), so that Write of any of them cannot fail for
  // want of space. Throws std::bad_alloc (memory) or std::system_error (a
  // file that cannot grow: a full disk) and then holds what it held.
  virtual void Reserve(size_t rows) = 0;
  // Rows [first, first + count) := values (count × width floats); the rows
  // are reserved. Throws std::system_error on an I/O error (then the rows'
  // contents are unknown, the others' unchanged).
  virtual void Write(size_t first, size_t count, const float* values) = 0;
  // values (count × width floats) := rows [first, first + count), which
  // were written. Throws std::system_error on an I/O error.
  virtual void Read(size_t first, size_t count, float* values) const = 0;
  // values (rows.size() × width floats) := each of `rows` in turn (in any
  // order, repeats allowed), which were written: a search's candidates or
  // a sample's codes in one call. A store whose rows may be on disk
  // (FileFloatRows) starts every read it has to wait for before waiting
  // for the first, so that the call waits about as long as the slowest
  // read, not as long as all of them in turn. This one Reads each row.
  // Throws std::system_error on an I/O error.
  virtual void Gather(std::span<const uint32_t> rows, float* values) const;
  // Rows [0, rows) but those in `keep` (ascending, each below `rows`) :=
  // the rows lying in `file` from `offset` on (width floats each, as Write
  // takes them), read from there from now on instead of copied: a graph
  // loaded from its mapped snapshot, or one just saved to a file, whose
  // rows written since are `keep`. `checks`, if not empty, holds each
  // row's RowCheck (rows the file's own checksum does not cover: a row
  // read from the file that fails it is a std::system_error of
  // std::errc::bad_message, never returned); empty, the file was checked
  // whole. Rows past them and in `keep` keep what they held; a row written
  // later is this store's own again. True if this store took them (what
  // it held for them is dropped); false (the default) if it keeps its rows
  // elsewhere: then nothing changed, and a caller loading them Writes them.
  virtual bool Adopt(const FileBytes& file, uint64_t offset, size_t rows,
                     std::span<const uint32_t> keep,
                     std::span<const uint32_t> checks) {
    return false;
  }
  // Row `row` where it lies in this process's memory, or nullptr if this
  // store keeps its rows elsewhere (Read copies them).
  virtual const float* Find(size_t row) const { return nullptr; }
  // Bytes of the process's own memory holding rows (a file's page cache is
  // the kernel's, not counted).
  virtual size_t MemoryBytes() const = 0;

 private:
  size_t width_;
};

// A row's checksum (the low 32 bits of XXH3-64 of its bytes), which an
// int8 graph's snapshot keeps beside its floats so that a row read from the
// snapshot's file is checked when it is read, not when the file is.
uint32_t RowCheck(std::span<const float> row);

// Makes the rows of a graph: `width` floats a row.
using FloatRowsMaker = std::function<std::unique_ptr<FloatRows>(size_t width)>;

// Rows on the heap in blocks of kBlockRows that never move as rows are
// added (a pointer Find returned stays valid while the rows live).
class MemoryFloatRows final : public FloatRows {
 public:
  static constexpr size_t kBlockRows = 4096;
  explicit MemoryFloatRows(size_t width) : FloatRows(width) {}
  void Reserve(size_t rows) override;
  void Write(size_t first, size_t count, const float* values) override;
  void Read(size_t first, size_t count, float* values) const override;
  const float* Find(size_t row) const override;
  size_t MemoryBytes() const override;

 private:
  std::vector<std::unique_ptr<float[]>> blocks_;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_FLOAT_ROWS_H_
