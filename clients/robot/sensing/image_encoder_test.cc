#include "clients/robot/sensing/image_encoder.h"

#include <cmath>
#include <set>
#include <string>
#include <vector>

#include "clients/robot/sensing/code_search.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot {
namespace {

using ::testing::Each;
using ::testing::FloatNear;
using ::testing::HasSubstr;

cv::Mat RandomImage(int seed) {
  cv::Mat image(32, 64, CV_8UC1);
  cv::RNG rng(seed);
  rng.fill(image, cv::RNG::UNIFORM, 20, 200);
  return image;
}

TEST(PatchNormEncoderTest, EveryPatchHasZeroMeanAndUnitVariance) {
  const auto encoder =
      NewPatchNormEncoder({.width = 32, .height = 16, .patch = 8});
  ASSERT_NE(encoder, nullptr);
  EXPECT_EQ(encoder->dimension(), 512u);
  EXPECT_EQ(encoder->version(), "patchnorm-32x16-p8-v1");
  absl::StatusOr<std::vector<float>> code =
      encoder->EncodeImage(RandomImage(1));
  ASSERT_TRUE(code.ok()) << code.status();
  ASSERT_EQ(code->size(), 512u);
  // Row-major 32x16 thumbnail; patch (px, py) covers 8x8 of it.
  for (int py = 0; py < 2; ++py) {
    for (int px = 0; px < 4; ++px) {
      double sum = 0.0, squares = 0.0;
      for (int y = 0; y < 8; ++y) {
        for (int x = 0; x < 8; ++x) {
          const float v = (*code)[(py * 8 + y) * 32 + px * 8 + x];
          sum += v;
          squares += v * v;
        }
      }
      EXPECT_NEAR(sum / 64, 0.0, 1e-4);
      EXPECT_NEAR(squares / 64, 1.0, 1e-3);
    }
  }
}

TEST(PatchNormEncoderTest, IgnoresBrightnessAndContrast) {
  const auto encoder = NewPatchNormEncoder({});
  const cv::Mat image = RandomImage(2);
  cv::Mat brighter;
  image.convertTo(brighter, CV_8UC1, 1.2, 10);  // stays below 255
  absl::StatusOr<std::vector<float>> a = encoder->EncodeImage(image);
  absl::StatusOr<std::vector<float>> b = encoder->EncodeImage(brighter);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_LT(CodeDistance(*a, *b), 0.05f);
}

TEST(PatchNormEncoderTest, BlackFrameGivesZeros) {
  const auto encoder = NewPatchNormEncoder({});
  absl::StatusOr<std::vector<float>> code =
      encoder->EncodeImage(cv::Mat::zeros(32, 64, CV_8UC1));
  ASSERT_TRUE(code.ok());
  EXPECT_THAT(*code, Each(0.0f));
}

TEST(PatchNormEncoderTest, RejectsBadOptions) {
  EXPECT_EQ(NewPatchNormEncoder({.width = 30, .height = 16, .patch = 8}),
            nullptr);
  EXPECT_EQ(NewPatchNormEncoder({.width = 32, .height = 16, .patch = 0}),
            nullptr);
}

TEST(HogEncoderTest, DimensionMatchesTheLayout) {
  // 64x32 window, 16x16 blocks every 8 pixels: 7 x 3 blocks of 4 cells.
  const auto encoder = NewHogEncoder(
      {.width = 64, .height = 32, .cell = 8, .block_stride = 8, .bins = 6});
  ASSERT_NE(encoder, nullptr);
  EXPECT_EQ(encoder->dimension(), 7u * 3u * 4u * 6u);
  absl::StatusOr<std::vector<float>> code =
      encoder->EncodeImage(RandomImage(3));
  ASSERT_TRUE(code.ok()) << code.status();
  EXPECT_EQ(code->size(), encoder->dimension());
  // Another image gives another code.
  absl::StatusOr<std::vector<float>> other =
      encoder->EncodeImage(RandomImage(4));
  ASSERT_TRUE(other.ok());
  EXPECT_GT(CodeDistance(*code, *other), 0.1f);
}

TEST(HogEncoderTest, RejectsBadOptions) {
  EXPECT_EQ(
      NewHogEncoder({.width = 64, .height = 32, .cell = 8, .block_stride = 12}),
      nullptr);
  EXPECT_EQ(NewHogEncoder({.width = 8, .height = 32, .cell = 8}), nullptr);
}

TEST(ImageEncoderTest, RejectsNonGreyImages) {
  for (const std::string& name : ImageEncoderNames()) {
    absl::StatusOr<std::unique_ptr<ImageEncoder>> encoder =
        NewImageEncoderByName(name);
    ASSERT_TRUE(encoder.ok());
    EXPECT_EQ((*encoder)->EncodeImage(cv::Mat()).status().code(),
              absl::StatusCode::kInvalidArgument)
        << name;
    EXPECT_EQ((*encoder)->EncodeImage(cv::Mat(32, 64, CV_8UC3)).status().code(),
              absl::StatusCode::kInvalidArgument)
        << name;
  }
}

TEST(NewImageEncoderByNameTest, EveryNameMakesADistinctEncoder) {
  std::set<std::string> versions;
  for (const std::string& name : ImageEncoderNames()) {
    absl::StatusOr<std::unique_ptr<ImageEncoder>> encoder =
        NewImageEncoderByName(name);
    ASSERT_TRUE(encoder.ok()) << name;
    ASSERT_NE(*encoder, nullptr) << name;
    EXPECT_TRUE(versions.insert((*encoder)->version()).second) << name;
    absl::StatusOr<std::vector<float>> code =
        (*encoder)->EncodeImage(RandomImage(5));
    ASSERT_TRUE(code.ok()) << name;
    EXPECT_EQ(code->size(), (*encoder)->dimension()) << name;
  }
  const absl::StatusOr<std::unique_ptr<ImageEncoder>> unknown =
      NewImageEncoderByName("sift");
  EXPECT_EQ(unknown.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(unknown.status().message(), HasSubstr("hog-64x32-c8-s8-b6"));
}

}  // namespace
}  // namespace fleetmem::robot
