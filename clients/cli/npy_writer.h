// NumPy .npy files (format version 1.0), the arrays place-recognition
// evaluation scripts load with numpy.load: little-endian float32 or float64,
// C order, written to FILE.tmp and renamed, so a reader never sees half a
// file.
#ifndef FLEETMEM_CLIENTS_CLI_NPY_WRITER_H_
#define FLEETMEM_CLIENTS_CLI_NPY_WRITER_H_

#include <cstddef>
#include <span>
#include <string>

#include "absl/status/status.h"

namespace fleetmem::cli {

// The 10-byte preamble and the header dict, padded to a multiple of 64
// bytes: the bytes before the data of a rows x cols array of `descr`
// ("<f4", "<f8").
std::string NpyHeader(const std::string& descr, size_t rows, size_t cols);

// Writes `values` (rows x cols, row-major) to `path`. INVALID_ARGUMENT if
// values.size() != rows * cols; INTERNAL naming the path on an I/O error
// (nothing is left at `path` then).
absl::Status WriteNpy(const std::string& path, std::span<const float> values,
                      size_t rows, size_t cols);
absl::Status WriteNpy(const std::string& path, std::span<const double> values,
                      size_t rows, size_t cols);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_NPY_WRITER_H_
