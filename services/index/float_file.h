// An int8 place graph's floats (each code as given and its scale) in a file
// of their own, read and written with pread/pwrite: they live in the
// kernel's page cache, which keeps the pages a fleet's queries rescore and
// writes the others back, instead of the process's heap. The file is
// unlinked as soon as it is made, so nothing is left behind when the
// process ends (a crash included): it holds no state of its own, only what
// the graph (and its snapshot, which still carries the floats) holds.
#ifndef FLEETMEM_SERVICES_INDEX_FLOAT_FILE_H_
#define FLEETMEM_SERVICES_INDEX_FLOAT_FILE_H_

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>

#include "services/core/float_rows.h"

namespace fleetmem::index {

class FileFloatRows final : public core::FloatRows {
 public:
  // The file is made in `directory` (which must exist) by the first
  // Reserve.
  FileFloatRows(std::string directory, size_t width);
  ~FileFloatRows() override;

  // Makes the file if needed and allocates its blocks (posix_fallocate, a
  // quarter more than asked at a time), so that a Write into reserved rows
  // never meets a full disk. std::system_error when the file cannot be
  // made or grown (ENOSPC: a full disk); what was reserved stays.
  void Reserve(size_t rows) override;
  // std::system_error on an I/O error.
  void Write(size_t first, size_t count, const float* values) override;
  void Read(size_t first, size_t count, float* values) const override;
  // Each row the page cache holds is copied at once (preadv2 with
  // RWF_NOWAIT); the reads of the others are all started
  // (posix_fadvise(WILLNEED)) before the first is waited for (pread), so
  // that a search's 40 candidates or a sample's 1,000 codes cost about one
  // disk read's wait, not one per row (bench/cold_rows_ab.sh). Where the
  // kernel cannot read without waiting, each row is read in turn.
  void Gather(std::span<const uint32_t> rows, float* values) const override;
  size_t MemoryBytes() const override { return 0; }

  // Rows the file has room for (tests).
  size_t reserved() const { return reserved_; }

 private:
  std::string directory_;
  int fd_ = -1;
  size_t reserved_ = 0;
  // Cleared when preadv2 says RWF_NOWAIT is not supported here.
  mutable std::atomic<bool> nowait_ = true;
};

// A maker of FileFloatRows in `directory` (core::HnswGraphOptions::float_rows).
core::FloatRowsMaker FloatRowsInFiles(std::string directory);

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_FLOAT_FILE_H_
