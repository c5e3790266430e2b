#include "clients/cli/npy_reader.h"

#include <fstream>
#include <string>
#include <vector>

#include "clients/cli/npy_writer.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/common/files.h"

namespace fleetmem::cli {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

// A file of `header` (NpyHeader's or a hand-made dict) followed by `data`.
void WriteRaw(const std::string& path, const std::string& header,
              const std::string& data) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << header << data;
}

std::string Bytes(const std::vector<double>& values) {
  return std::string(reinterpret_cast<const char*>(values.data()),
                     values.size() * sizeof(double));
}

TEST(NpyReaderTest, ReadsWhatTheExportWritesByRowsInEitherType) {
  files::TempDir dir;
  ASSERT_TRUE(dir.status().ok()) << dir.status();
  const std::string path = dir.Join("codes.npy");
  const std::vector<float> values = {1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12};
  ASSERT_TRUE(WriteNpy(path, values, 4, 3).ok());
  absl::StatusOr<NpyReader> reader = NpyReader::Open(path);
  ASSERT_TRUE(reader.ok()) << reader.status();
  EXPECT_EQ(reader->rows(), 4u);
  EXPECT_EQ(reader->cols(), 3u);
  std::vector<float> floats;
  ASSERT_TRUE(reader->ReadRows(1, 2, &floats).ok());
  EXPECT_THAT(floats, ElementsAre(4, 5, 6, 7, 8, 9));
  std::vector<double> doubles = {-1};
  ASSERT_TRUE(reader->ReadRows(3, 1, &doubles).ok());  // appended
  EXPECT_THAT(doubles, ElementsAre(-1, 10, 11, 12));
  const absl::Status past = reader->ReadRows(3, 2, &floats);
  EXPECT_EQ(past.code(), absl::StatusCode::kOutOfRange) << past;
}

TEST(NpyReaderTest, ReadsAOneDimensionalFloat64ArrayAsOneColumn) {
  files::TempDir dir;
  const std::string path = dir.Join("rewards.npy");
  std::string header =
      "{'descr': '<f8', 'fortran_order': False, 'shape': (3,), }";
  header.append((64 - (10 + header.size() + 1) % 64) % 64, ' ');
  header.push_back('\n');
  WriteRaw(path,
           std::string("\x93NUMPY\x01\x00", 8) +
               static_cast<char>(header.size()) + '\0' + header,
           Bytes({0.5, 1.5, 2.5}));
  absl::StatusOr<NpyReader> reader = NpyReader::Open(path);
  ASSERT_TRUE(reader.ok()) << reader.status();
  EXPECT_EQ(reader->rows(), 3u);
  EXPECT_EQ(reader->cols(), 1u);
  std::vector<float> rewards;
  ASSERT_TRUE(reader->ReadRows(0, 3, &rewards).ok());
  EXPECT_THAT(rewards, ElementsAre(0.5f, 1.5f, 2.5f));
}

TEST(NpyReaderTest, RefusesWhatItCannotReadNamingWhy) {
  EXPECT_EQ(NpyReader::Open("/nonexistent/codes.npy").status().code(),
            absl::StatusCode::kNotFound);
  files::TempDir dir;
  const std::string path = dir.Join("bad.npy");
  struct Case {
    std::string header;
    std::string data;
    std::string says;
  };
  const std::vector<Case> cases = {
      {"not an npy file at all", "", "no .npy preamble"},
      {NpyHeader("<i4", 2, 2), std::string(16, '\0'), "dtype '<i4'"},
      {NpyHeader("<f8", 2, 2), std::string(31, '\0'), "header says 160"},
  };
  for (const Case& c : cases) {
    WriteRaw(path, c.header, c.data);
    const absl::Status status = NpyReader::Open(path).status();
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
    EXPECT_THAT(std::string(status.message()), HasSubstr(c.says));
    EXPECT_THAT(std::string(status.message()), HasSubstr(path));
  }
  EXPECT_THAT(
      ParseNpyDict("{'descr': '<f4', 'fortran_order': True, 'shape': (2, 2), }")
          .status()
          .message(),
      HasSubstr("Fortran order"));
  EXPECT_THAT(
      ParseNpyDict(
          "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2, 2), }")
          .status()
          .message(),
      HasSubstr("3 dimensions"));
  absl::StatusOr<NpyShape> shape = ParseNpyDict(
      "{'descr': '<f8', 'fortran_order': False, 'shape': (7, 256), }");
  ASSERT_TRUE(shape.ok()) << shape.status();
  EXPECT_TRUE(shape->doubles);
  EXPECT_EQ(shape->rows, 7u);
  EXPECT_EQ(shape->cols, 256u);
}

}  // namespace
}  // namespace fleetmem::cli
