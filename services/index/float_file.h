// An int8 place graph's floats (each code as given and its scale) in a file
// of their own, read and written with pread/pwrite: they live in the
// kernel's page cache, which keeps the pages a fleet's queries rescore and
// writes the others back, instead of the process's heap. The file is
// unlinked as soon as it is made, so nothing is left behind when the
// process ends (a crash included): it holds no state of its own, only what
// the graph (and its snapshot, which still carries the floats) holds.
//
// Adopted rows (Adopt: a graph loaded from its index snapshot, or one just
// saved to it) are read from the snapshot's file itself, held open, until
// they are written again: a start copies no float, and the rows' disk and
// page cache are the snapshot's. Their own file then holds only the rows
// written since (a sparse file: a hole under each adopted row). Adopted
// with their checks (a snapshot's file that leaves the floats out of its
// checksum), each row read from the file is checked first: a row that
// fails is a std::system_error (std::errc::bad_message) naming it.
#ifndef FLEETMEM_SERVICES_INDEX_FLOAT_FILE_H_
#define FLEETMEM_SERVICES_INDEX_FLOAT_FILE_H_

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "services/core/byte_stream.h"
#include "services/core/float_rows.h"

namespace fleetmem::index {

class FileFloatRows final : public core::FloatRows {
 public:
  // The file is made in `directory` (which must exist) by the first
  // Reserve.
  FileFloatRows(std::string directory, size_t width);
  ~FileFloatRows() override;

  // Makes the file if needed and allocates its blocks past the adopted
  // rows (posix_fallocate, a quarter more than asked at a time), so that a
  // Write into reserved rows never meets a full disk. std::system_error
  // when the file cannot be made or grown (ENOSPC: a full disk); what was
  // reserved stays.
  void Reserve(size_t rows) override;
  // std::system_error on an I/O error; an adopted row's first Write takes
  // its block then (ENOSPC on a full disk: the row still reads as adopted).
  void Write(size_t first, size_t count, const float* values) override;
  void Read(size_t first, size_t count, float* values) const override;
  // Each row the page cache holds is copied at once (preadv2 with
  // RWF_NOWAIT); the reads of the others are all started
  // (posix_fadvise(WILLNEED)) before the first is waited for (pread), so
  // that a search's 40 candidates or a sample's 1,000 codes cost about one
  // disk read's wait, not one per row (bench/cold_rows_ab.sh). Where the
  // kernel cannot read without waiting, each row is read in turn.
  void Gather(std::span<const uint32_t> rows, float* values) const override;

  // Drops the copies of the rows below `rows` but `keep` (their blocks in
  // the file: holes punched) and reads them from `file` at `offset` until
  // each is written again. True unless `file` has no descriptor.
  bool Adopt(const core::FileBytes& file, uint64_t offset, size_t rows,
             std::span<const uint32_t> keep,
             std::span<const uint32_t> checks) override;
  // The bitmap of adopted rows written since, and their checks.
  size_t MemoryBytes() const override {
    return (adopted_ + 63) / 64 * 8 + checks_.capacity() * sizeof(uint32_t);
  }

  // Rows the file has room for (tests).
  size_t reserved() const { return reserved_; }
  // Rows read from an adopted file, and the bytes of their own file's
  // blocks (st_blocks: what the disk holds) (tests).
  size_t adopted() const { return adopted_; }
  size_t AllocatedBytes() const;

 private:
  // Where row `row` is read from: its own file or the adopted one.
  struct Place {
    int fd;
    off_t offset;
  };
  Place PlaceOf(size_t row) const;
  // Throws unless `values` (one row, read from `place`) passes its check,
  // where the row has one.
  void Check(size_t row, const Place& place, const float* values) const;
  // Makes the file if it is not made yet.
  void Open();

  std::string directory_;
  int fd_ = -1;
  size_t reserved_ = 0;
  // Rows [0, adopted_) are read from adopted_file_ at adopted_offset_
  // unless their bit in rewritten_ is set (a Write since).
  core::FileBytes adopted_file_;
  uint64_t adopted_offset_ = 0;
  size_t adopted_ = 0;
  std::unique_ptr<std::atomic<uint64_t>[]> rewritten_;
  // Each adopted row's core::RowCheck; empty when the file was checked.
  std::vector<uint32_t> checks_;
  // Cleared when preadv2 says RWF_NOWAIT is not supported here.
  mutable std::atomic<bool> nowait_ = true;
};

// A maker of FileFloatRows in `directory` (core::HnswGraphOptions::float_rows).
core::FloatRowsMaker FloatRowsInFiles(std::string directory);

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_FLOAT_FILE_H_
