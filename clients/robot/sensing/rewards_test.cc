#include "clients/robot/sensing/rewards.h"

#include <cmath>
#include <random>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot {
namespace {

using ::testing::ElementsAre;
using ::testing::FloatNear;

// A 64x32 image whose value grows with the column: any horizontal shift
// changes it.
cv::Mat Ramp() {
  cv::Mat image(32, 64, CV_8UC1);
  for (int y = 0; y < image.rows; ++y) {
    for (int x = 0; x < image.cols; ++x) image.at<uint8_t>(y, x) = 4 * x;
  }
  return image;
}

TEST(RandomShiftCropTest, KeepsTheSizeAndMovesTheContent) {
  std::mt19937_64 rng(1);
  const cv::Mat image = Ramp();
  int changed = 0;
  for (int i = 0; i < 10; ++i) {
    absl::StatusOr<cv::Mat> moved =
        RandomShiftCrop(image, ShiftCropOptions{}, rng);
    ASSERT_TRUE(moved.ok()) << moved.status();
    EXPECT_EQ(moved->size(), image.size());
    EXPECT_EQ(moved->type(), image.type());
    changed += cv::norm(*moved, image, cv::NORM_L1) > 0 ? 1 : 0;
  }
  EXPECT_GT(changed, 0);
}

TEST(RandomShiftCropTest, NoShiftIsTheIdentity) {
  std::mt19937_64 rng(1);
  const cv::Mat image = Ramp();
  absl::StatusOr<cv::Mat> moved =
      RandomShiftCrop(image, {.max_shift_x = 0, .max_shift_y = 0}, rng);
  ASSERT_TRUE(moved.ok());
  EXPECT_EQ(cv::norm(*moved, image, cv::NORM_L1), 0.0);
}

TEST(RandomShiftCropTest, RejectsMarginsLargerThanTheImage) {
  std::mt19937_64 rng(1);
  EXPECT_EQ(RandomShiftCrop(Ramp(), {.max_shift_x = 32, .max_shift_y = 0}, rng)
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(RandomShiftCrop(cv::Mat(), {}, rng).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(InternalRewardTest, IsOneMinusCosine) {
  const std::vector<float> a = {1, 0}, b = {0, 1}, c = {2, 0};
  EXPECT_THAT(InternalReward(a, c), FloatNear(0.0f, 1e-6f));
  EXPECT_THAT(InternalReward(a, b), FloatNear(1.0f, 1e-6f));
}

// Codes on the unit circle at angle `degrees`, so distances are chords.
std::vector<float> At(double degrees) {
  const double r = degrees * M_PI / 180.0;
  return {static_cast<float>(std::cos(r)), static_cast<float>(std::sin(r))};
}

float Chord(double degrees) {
  return static_cast<float>(2.0 * std::sin(degrees * M_PI / 360.0));
}

TEST(ExternalRewardsTest, IsTheTripletLossOfHardestPairs) {
  // Frames at route positions 0, 10, 20, 200. Frame 0's positive (within
  // 10) is frame 10; its negatives (beyond 100) are frame 200 only.
  const std::vector<std::vector<float>> codes = {At(0), At(60), At(65), At(10)};
  const std::vector<core::Place> x = {
      {.x = 0}, {.x = 10}, {.x = 20}, {.x = 200}};
  const TripletOptions options{
      .margin = 0.1, .positive_radius = 10, .negative_radius = 100};
  const std::vector<float> rewards = ExternalRewards(codes, x, options);
  ASSERT_EQ(rewards.size(), 4u);
  // Frame 0: d(pos) = chord(60), d(neg) = chord(10): a hard sample.
  EXPECT_THAT(rewards[0], FloatNear(Chord(60) - Chord(10) + 0.1f, 1e-5f));
  // Frame 2: pos = frame 1 (5 degrees), neg = frame 3 (55 degrees): easy.
  EXPECT_THAT(rewards[2], FloatNear(0.0f, 1e-6f));
  // Frame 3: no positive (d = 0); hardest negative = frame 0 (10 degrees).
  EXPECT_THAT(rewards[3], FloatNear(std::max(0.0f, 0.1f - Chord(10)), 1e-6f));
}

TEST(ExternalRewardsTest, MeasuresDistancesInThePlane) {
  // Scans 3 m apart in y are negatives at a 2 m radius, whatever x says.
  const std::vector<std::vector<float>> codes = {At(0), At(10)};
  const std::vector<core::Place> places = {{.x = 0, .y = 0}, {.x = 0, .y = 3}};
  const std::vector<float> rewards = ExternalRewards(
      codes, places,
      {.margin = 0.5, .positive_radius = 1.0, .negative_radius = 2.0});
  EXPECT_THAT(rewards[0], FloatNear(0.5f - Chord(10), 1e-5f));
}

TEST(ExternalRewardsTest, NoNegativeMeansZero) {
  const std::vector<std::vector<float>> codes = {At(0), At(90)};
  const std::vector<core::Place> x = {{.x = 0}, {.x = 10}};
  EXPECT_THAT(ExternalRewards(codes, x, TripletOptions{}), ElementsAre(0, 0));
}

TEST(ExternalRewardsTest, MismatchedSizesGiveNothing) {
  const std::vector<std::vector<float>> codes = {At(0), At(90)};
  const std::vector<core::Place> x = {{.x = 0}};
  EXPECT_TRUE(ExternalRewards(codes, x, TripletOptions{}).empty());
}

}  // namespace
}  // namespace fleetmem::robot
