#include "clients/cli/npy_reader.h"

#include <cstdint>
#include <cstring>
#include <filesystem>
#include <system_error>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"

namespace fleetmem::cli {
namespace {

static_assert(sizeof(float) == 4 && sizeof(double) == 8);

// The value after "'key':" in the header dict, up to the next top-level
// comma (a shape's tuple whole); empty if the key is missing.
std::string DictValue(const std::string& dict, const std::string& key) {
  const std::string quoted = "'" + key + "'";
  size_t at = dict.find(quoted);
  if (at == std::string::npos) return "";
  at = dict.find(':', at + quoted.size());
  if (at == std::string::npos) return "";
  ++at;
  int depth = 0;
  size_t end = at;
  for (; end < dict.size(); ++end) {
    const char c = dict[end];
    if (c == '(') ++depth;
    if (c == ')') --depth;
    if ((c == ',' && depth == 0) || c == '}') break;
  }
  return std::string(absl::StripAsciiWhitespace(dict.substr(at, end - at)));
}

}  // namespace

absl::StatusOr<NpyShape> ParseNpyDict(const std::string& dict) {
  NpyShape shape;
  const std::string descr = DictValue(dict, "descr");
  if (descr == "'<f4'") {
    shape.doubles = false;
  } else if (descr == "'<f8'") {
    shape.doubles = true;
  } else {
    return absl::InvalidArgumentError(
        absl::StrCat("dtype ", descr.empty() ? "(none)" : descr,
                     " is not supported; save the array as float32 or float64 "
                     "(little-endian)"));
  }
  if (DictValue(dict, "fortran_order") != "False") {
    return absl::InvalidArgumentError(
        "the array is in Fortran order; save a C-ordered array "
        "(numpy.ascontiguousarray)");
  }
  std::string tuple = DictValue(dict, "shape");
  if (tuple.size() < 2 || tuple.front() != '(' || tuple.back() != ')') {
    return absl::InvalidArgumentError("the header has no shape");
  }
  std::vector<size_t> dims;
  for (absl::string_view part :
       absl::StrSplit(tuple.substr(1, tuple.size() - 2), ',')) {
    part = absl::StripAsciiWhitespace(part);
    if (part.empty()) continue;
    uint64_t value = 0;
    if (!absl::SimpleAtoi(part, &value)) {
      return absl::InvalidArgumentError(
          absl::StrCat("the shape ", tuple, " is not a tuple of sizes"));
    }
    dims.push_back(static_cast<size_t>(value));
  }
  if (dims.empty() || dims.size() > 2) {
    return absl::InvalidArgumentError(absl::StrCat(
        "the shape ", tuple, " has ", dims.size(),
        " dimensions; one or two are read (rows, or rows x columns)"));
  }
  shape.rows = dims[0];
  shape.cols = dims.size() == 2 ? dims[1] : 1;
  return shape;
}

absl::StatusOr<NpyReader> NpyReader::Open(const std::string& path) {
  NpyReader reader;
  reader.path_ = path;
  reader.in_ = std::make_unique<std::ifstream>(path, std::ios::binary);
  if (!*reader.in_) {
    return absl::NotFoundError(absl::StrCat("cannot open ", path));
  }
  const auto invalid = [&](std::string_view what) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ": not a readable .npy array: ",
                     absl::string_view(what.data(), what.size())));
  };
  char preamble[10];
  if (!reader.in_->read(preamble, sizeof(preamble)) ||
      std::memcmp(preamble, "\x93NUMPY", 6) != 0) {
    return invalid("no .npy preamble");
  }
  const int major = static_cast<unsigned char>(preamble[6]);
  size_t header_length = 0;
  size_t prefix = 10;
  if (major == 1) {
    header_length =
        static_cast<unsigned char>(preamble[8]) |
        (static_cast<size_t>(static_cast<unsigned char>(preamble[9])) << 8);
  } else if (major == 2 || major == 3) {
    char more[2];
    if (!reader.in_->read(more, 2)) return invalid("truncated header");
    const unsigned char bytes[4] = {static_cast<unsigned char>(preamble[8]),
                                    static_cast<unsigned char>(preamble[9]),
                                    static_cast<unsigned char>(more[0]),
                                    static_cast<unsigned char>(more[1])};
    header_length = bytes[0] | (size_t{bytes[1]} << 8) |
                    (size_t{bytes[2]} << 16) | (size_t{bytes[3]} << 24);
    prefix = 12;
  } else {
    return invalid(absl::StrCat("format version ", major, " is not known"));
  }
  std::string dict(header_length, '\0');
  if (!reader.in_->read(dict.data(),
                        static_cast<std::streamsize>(header_length))) {
    return invalid("truncated header");
  }
  absl::StatusOr<NpyShape> shape = ParseNpyDict(dict);
  if (!shape.ok()) return invalid(std::string(shape.status().message()));
  reader.data_offset_ = prefix + header_length;
  reader.rows_ = shape->rows;
  reader.cols_ = shape->cols;
  reader.doubles_ = shape->doubles;
  std::error_code error;
  const uintmax_t size = std::filesystem::file_size(path, error);
  const size_t want = reader.data_offset_ +
                      reader.rows_ * reader.cols_ * (reader.doubles_ ? 8 : 4);
  if (error || size != want) {
    return invalid(absl::StrCat("the file has ", error ? 0 : size,
                                " bytes; its header says ", want));
  }
  return reader;
}

template <typename T>
absl::Status NpyReader::Read(size_t first, size_t count, std::vector<T>* out) {
  if (first > rows_ || count > rows_ - first) {
    return absl::OutOfRangeError(absl::StrCat(path_, ": rows ", first, "..",
                                              first + count, " of ", rows_));
  }
  const size_t values = count * cols_;
  const size_t width = doubles_ ? 8 : 4;
  in_->clear();
  in_->seekg(static_cast<std::streamoff>(data_offset_ + first * cols_ * width));
  const size_t at = out->size();
  out->resize(at + values);
  if (doubles_ == (sizeof(T) == 8)) {
    // x86-64 and arm64 are little-endian, as '<f4'/'<f8' are.
    in_->read(reinterpret_cast<char*>(out->data() + at),
              static_cast<std::streamsize>(values * width));
  } else {
    std::vector<char> raw(values * width);
    in_->read(raw.data(), static_cast<std::streamsize>(raw.size()));
    for (size_t i = 0; i < values; ++i) {
      if (doubles_) {
        double value;
        std::memcpy(&value, raw.data() + i * 8, 8);
        (*out)[at + i] = static_cast<T>(value);
      } else {
        float value;
        std::memcpy(&value, raw.data() + i * 4, 4);
        (*out)[at + i] = static_cast<T>(value);
      }
    }
  }
  if (!*in_) {
    out->resize(at);
    return absl::InternalError(absl::StrCat("cannot read ", path_));
  }
  return absl::OkStatus();
}

absl::Status NpyReader::ReadRows(size_t first, size_t count,
                                 std::vector<float>* out) {
  return Read(first, count, out);
}

absl::Status NpyReader::ReadRows(size_t first, size_t count,
                                 std::vector<double>* out) {
  return Read(first, count, out);
}

}  // namespace fleetmem::cli
