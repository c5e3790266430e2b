#include "clients/robot/sensing/nordland.h"

#include <filesystem>
#include <string>

#include "fleetmem_paths.h"
#include "gtest/gtest.h"

namespace fleetmem::robot {
namespace {

// The real recordings (read-only), ../shared/data beside the project.
std::string SeasonDir(const std::string& season) {
  return std::string(FLEETMEM_DATA_DIR) + "/nordland/" + season;
}

TEST(NordlandFileNameTest, PadsToFiveDigits) {
  EXPECT_EQ(NordlandFileName(10), "images-00010.png");
  EXPECT_EQ(NordlandFileName(12340), "images-12340.png");
}

TEST(ListNordlandFramesTest, ListsTheRealRoute) {
  if (!std::filesystem::exists(SeasonDir("summer"))) {
    GTEST_SKIP() << "no Nordland data at " << SeasonDir("summer");
  }
  for (const char* season : {"summer", "winter"}) {
    absl::StatusOr<std::vector<int>> frames =
        ListNordlandFrames(SeasonDir(season));
    ASSERT_TRUE(frames.ok()) << frames.status();
    ASSERT_EQ(frames->size(), 2500u) << season;
    EXPECT_EQ(frames->front(), 10);
    EXPECT_EQ(frames->back(), 25000);
    EXPECT_TRUE(std::is_sorted(frames->begin(), frames->end()));
  }
}

TEST(LoadNordlandGreyTest, LoadsOneGreyThumbnail) {
  if (!std::filesystem::exists(SeasonDir("summer"))) {
    GTEST_SKIP() << "no Nordland data at " << SeasonDir("summer");
  }
  absl::StatusOr<cv::Mat> image = LoadNordlandGrey(SeasonDir("summer"), 12340);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->cols, 64);
  EXPECT_EQ(image->rows, 32);
  EXPECT_EQ(image->type(), CV_8UC1);
  EXPECT_EQ(LoadNordlandGrey(SeasonDir("summer"), 12345).status().code(),
            absl::StatusCode::kNotFound);
}

// image_decode_fuzz found bytes that OpenCV hands to Debian's DICOM decoder,
// which aborts: only PNG and JPEG signatures are decoded.
TEST(DecodeGreyTest, OnlyPngAndJpegAreDecoded) {
  const std::string dicom_like =
      std::string(128, '\0') + "DICM" + std::string(16, '\xa3');
  absl::StatusOr<cv::Mat> decoded = DecodeGrey(dicom_like, "x.dcm");
  EXPECT_EQ(decoded.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(decoded.status().message().find("not a PNG or JPEG"),
            std::string::npos);
  const std::string truncated_png("\x89PNG\r\n\x1a\n\0\0", 10);
  EXPECT_EQ(DecodeGrey(truncated_png, "t.png").status().code(),
            absl::StatusCode::kDataLoss);
}

TEST(ListNordlandFramesTest, MissingFolderIsNotFound) {
  EXPECT_EQ(ListNordlandFrames("/nonexistent/nordland").status().code(),
            absl::StatusCode::kNotFound);
}

TEST(SpreadStretchesTest, SpreadsDisjointStretchesEvenly) {
  absl::StatusOr<std::vector<Stretch>> stretches =
      SpreadStretches(2500, 3, 300);
  ASSERT_TRUE(stretches.ok());
  ASSERT_EQ(stretches->size(), 3u);
  EXPECT_EQ((*stretches)[0].begin, 0u);
  EXPECT_EQ((*stretches)[1].begin, 833u);
  EXPECT_EQ((*stretches)[2].begin, 1666u);
  for (const Stretch& s : *stretches) EXPECT_EQ(s.end - s.begin, 300u);
}

TEST(SpreadStretchesTest, FillsTheRouteExactly) {
  for (int count : {1, 2, 3, 7}) {
    const size_t total = 100;
    const int length = static_cast<int>(total) / count;
    absl::StatusOr<std::vector<Stretch>> stretches =
        SpreadStretches(total, count, length);
    ASSERT_TRUE(stretches.ok()) << count;
    for (size_t i = 0; i < stretches->size(); ++i) {
      EXPECT_LE((*stretches)[i].end, total);
      if (i > 0) EXPECT_LE((*stretches)[i - 1].end, (*stretches)[i].begin);
    }
  }
}

TEST(SpreadStretchesTest, RejectsWhatDoesNotFit) {
  EXPECT_FALSE(SpreadStretches(2500, 3, 900).ok());
  EXPECT_FALSE(SpreadStretches(2500, 0, 300).ok());
  EXPECT_FALSE(SpreadStretches(2500, 3, 0).ok());
}

}  // namespace
}  // namespace fleetmem::robot
