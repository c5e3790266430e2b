#include "clients/robot/sensing/carmen_log.h"

#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/common/files.h"

namespace fleetmem::robot {
namespace {

using ::testing::HasSubstr;

const std::string kLaser = std::string(FLEETMEM_DATA_DIR) + "/laser";

TEST(CarmenLogTest, ReadsEveryFlaserRecordOfTheRealAcesLog) {
  absl::StatusOr<std::string> text = ReadMaybeBzip2(kLaser + "/aces.clf.bz2");
  ASSERT_TRUE(text.ok()) << text.status();
  absl::StatusOr<std::vector<Observation>> scans =
      ParseCarmenLog(*text, "aces.clf");
  ASSERT_TRUE(scans.ok()) << scans.status();
  ASSERT_EQ(scans->size(), 7374u);  // `bzcat | grep -c ^FLASER`
  const Observation& first = scans->front();
  EXPECT_EQ(first.name, "aces.clf:15");
  ASSERT_EQ(first.scan.ranges.size(), 180u);
  EXPECT_FLOAT_EQ(first.scan.ranges[0], 46.56f);
  EXPECT_FLOAT_EQ(first.scan.ranges[1], 47.31f);
  EXPECT_EQ(first.timestamp_ns, 70'289'900'000);
  EXPECT_TRUE(first.image.empty());
  for (size_t i = 1; i < scans->size(); ++i) {
    ASSERT_EQ((*scans)[i].index, i);
    ASSERT_GE((*scans)[i].timestamp_ns, (*scans)[i - 1].timestamp_ns) << i;
  }
}

TEST(CarmenLogTest, ReadsTheRealIntelLog) {
  absl::StatusOr<std::string> text = ReadMaybeBzip2(kLaser + "/intel.clf.bz2");
  ASSERT_TRUE(text.ok()) << text.status();
  absl::StatusOr<std::vector<Observation>> scans =
      ParseCarmenLog(*text, "intel.clf");
  ASSERT_TRUE(scans.ok()) << scans.status();
  EXPECT_EQ(scans->size(), 13631u);
}

TEST(CarmenLogTest, NamesTheFileAndLineOfABadRecord) {
  const std::string text =
      "# a comment\n"
      "FLASER 3 1.0 2.0 3.0 0.5 0.25 0.1 0 0 0 12.5 host 0.1\n"
      "ODOM 0 0 0 0 0 0 1 host 1\n"
      "FLASER 3 1.0 oops 3.0 0.5 0.25 0.1 0 0 0 12.6 host 0.2\n";
  absl::StatusOr<std::vector<Observation>> scans =
      ParseCarmenLog(text, "run.clf");
  ASSERT_EQ(scans.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(scans.status().message(), HasSubstr("run.clf:4: range 2"));

  scans = ParseCarmenLog("FLASER 180 1.0 2.0\n", "cut.clf");
  ASSERT_EQ(scans.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(scans.status().message(),
              HasSubstr("cut.clf:1: FLASER with 180 beams needs 189 fields"));

  scans = ParseCarmenLog("ODOM 0 0 0\n", "empty.clf");
  EXPECT_EQ(scans.status().code(), absl::StatusCode::kNotFound);
}

TEST(CarmenLogTest, ParsesThePose) {
  absl::StatusOr<std::vector<Observation>> scans = ParseCarmenLog(
      "FLASER 3 1.0 60.0 3.0 0.5 0.25 0.1 9 9 9 12.5 host 0.1\n", "p.clf");
  ASSERT_TRUE(scans.ok()) << scans.status();
  EXPECT_DOUBLE_EQ((*scans)[0].place.x, 0.5);
  EXPECT_DOUBLE_EQ((*scans)[0].place.y, 0.25);
  EXPECT_DOUBLE_EQ((*scans)[0].place.yaw, 0.1);
  EXPECT_EQ((*scans)[0].timestamp_ns, 12'500'000'000);
}

TEST(CarmenLogTest, ATruncatedBzip2FileIsDataLossNamingIt) {
  std::ifstream in(kLaser + "/aces.clf.bz2", std::ios::binary);
  std::string bytes((std::istreambuf_iterator<char>(in)),
                    std::istreambuf_iterator<char>());
  ASSERT_GT(bytes.size(), 1000u);
  files::TempDir dir("fleetmem-truncated-");
  const std::string path = dir.Join("aces.clf.bz2");
  std::ofstream(path, std::ios::binary) << bytes.substr(0, bytes.size() / 2);
  absl::StatusOr<std::string> text = ReadMaybeBzip2(path);
  ASSERT_EQ(text.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_THAT(text.status().message(), HasSubstr(path));
  EXPECT_THAT(text.status().message(), HasSubstr("truncated"));

  EXPECT_EQ(ReadMaybeBzip2("/nonexistent/x.clf.bz2").status().code(),
            absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace fleetmem::robot
