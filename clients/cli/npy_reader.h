// NumPy .npy files read a block of rows at a time: what `fleetmem import`
// loads (the export's codes.npy and places.npy, or any array numpy.save
// writes of that kind): format versions 1.0 to 3.0, C order, little-endian
// float32 or float64 ('<f4', '<f8'), one or two dimensions. Rows are read
// on demand, so a file larger than memory is fine.
#ifndef FLEETMEM_CLIENTS_CLI_NPY_READER_H_
#define FLEETMEM_CLIENTS_CLI_NPY_READER_H_

#include <cstddef>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fleetmem::cli {

class NpyReader {
 public:
  // NOT_FOUND if `path` cannot be opened; INVALID_ARGUMENT naming the file
  // and what does not fit (no .npy preamble, Fortran order, another dtype,
  // more than two dimensions, a length that is not the header's shape).
  static absl::StatusOr<NpyReader> Open(const std::string& path);

  const std::string& path() const { return path_; }
  size_t rows() const { return rows_; }
  // 1 for a one-dimensional array.
  size_t cols() const { return cols_; }

  // Appends rows [first, first + count) (row-major, converted to T) to
  // *out. OUT_OF_RANGE past the last row; INTERNAL naming the file on a
  // read error.
  absl::Status ReadRows(size_t first, size_t count, std::vector<float>* out);
  absl::Status ReadRows(size_t first, size_t count, std::vector<double>* out);

 private:
  template <typename T>
  absl::Status Read(size_t first, size_t count, std::vector<T>* out);

  std::string path_;
  std::unique_ptr<std::ifstream> in_;
  size_t data_offset_ = 0;
  size_t rows_ = 0;
  size_t cols_ = 1;
  bool doubles_ = false;  // '<f8' (else '<f4')
};

// The header's dict parsed (exposed for the tests): dtype, order and shape,
// or INVALID_ARGUMENT naming what is missing or not supported.
struct NpyShape {
  bool doubles = false;
  size_t rows = 0;
  size_t cols = 1;
};
absl::StatusOr<NpyShape> ParseNpyDict(const std::string& dict);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_NPY_READER_H_
