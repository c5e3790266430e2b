#include "clients/cli/npy_writer.h"

#include <cstdio>
#include <fstream>

#include "absl/strings/str_cat.h"

namespace fleetmem::cli {
namespace {

static_assert(sizeof(float) == 4 && sizeof(double) == 8);

template <typename T>
absl::Status Write(const std::string& path, std::span<const T> values,
                   size_t rows, size_t cols, const std::string& descr) {
  if (values.size() != rows * cols) {
    return absl::InvalidArgumentError(absl::StrCat(path, ": ", values.size(),
                                                   " values for a ", rows,
                                                   " x ", cols, " array"));
  }
  const std::string tmp = path + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    const std::string header = NpyHeader(descr, rows, cols);
    out.write(header.data(), static_cast<std::streamsize>(header.size()));
    // x86-64 and arm64 are little-endian, as "<f4"/"<f8" say.
    out.write(reinterpret_cast<const char*>(values.data()),
              static_cast<std::streamsize>(values.size() * sizeof(T)));
    out.flush();
    if (!out) {
      std::remove(tmp.c_str());
      return absl::InternalError(absl::StrCat("cannot write ", tmp));
    }
  }
  if (std::rename(tmp.c_str(), path.c_str()) != 0) {
    std::remove(tmp.c_str());
    return absl::InternalError(
        absl::StrCat("cannot rename ", tmp, " to ", path));
  }
  return absl::OkStatus();
}

}  // namespace

std::string NpyHeader(const std::string& descr, size_t rows, size_t cols) {
  std::string dict = absl::StrCat("{'descr': '", descr,
                                  "', 'fortran_order': False, 'shape': (", rows,
                                  ", ", cols, "), }");
  // Preamble (10 bytes) + dict + padding + '\n' is a multiple of 64.
  const size_t unpadded = 10 + dict.size() + 1;
  dict.append((64 - unpadded % 64) % 64, ' ');
  dict.push_back('\n');
  std::string header("\x93NUMPY\x01\x00", 8);
  header.push_back(static_cast<char>(dict.size() & 0xff));
  header.push_back(static_cast<char>((dict.size() >> 8) & 0xff));
  return header + dict;
}

absl::Status WriteNpy(const std::string& path, std::span<const float> values,
                      size_t rows, size_t cols) {
  return Write(path, values, rows, cols, "<f4");
}

absl::Status WriteNpy(const std::string& path, std::span<const double> values,
                      size_t rows, size_t cols) {
  return Write(path, values, rows, cols, "<f8");
}

}  // namespace fleetmem::cli
