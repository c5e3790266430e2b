#include <algorithm>
#include <set>

#include "clients/robot/sensing/carmen_log.h"
#include "clients/robot/sensing/encoder_factory.h"
#include "clients/robot/sensing/scan_encoder.h"
#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot {
namespace {

using ::testing::HasSubstr;

Observation Scan(std::vector<float> ranges) {
  Observation observation;
  observation.name = "scan";
  observation.scan.ranges = std::move(ranges);
  return observation;
}

Observation Image() {
  Observation observation;
  observation.name = "image";
  observation.image = cv::Mat(32, 64, CV_8UC1);
  cv::randu(observation.image, 0, 255);
  return observation;
}

TEST(EncoderTest, EveryEncoderHasADistinctVersionAndItsDimension) {
  std::set<std::string> versions;
  for (const std::string& name : EncoderNames()) {
    absl::StatusOr<std::unique_ptr<Encoder>> encoder = NewEncoderByName(name);
    ASSERT_TRUE(encoder.ok()) << encoder.status();
    EXPECT_THAT((*encoder)->version(), HasSubstr("-v1")) << name;
    EXPECT_TRUE(versions.insert((*encoder)->version()).second) << name;
    const bool scan = name.rfind("scan", 0) == 0;
    absl::StatusOr<std::vector<float>> code = (*encoder)->Encode(
        scan ? Scan(std::vector<float>(180, 3.0f)) : Image());
    ASSERT_TRUE(code.ok()) << name << ": " << code.status();
    EXPECT_EQ(code->size(), (*encoder)->dimension()) << name;
  }
  EXPECT_EQ(NewEncoderByName("sift").status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(EncoderTest, AnEncoderRefusesTheOtherKindOfObservation) {
  absl::StatusOr<std::unique_ptr<Encoder>> image =
      NewEncoderByName(EncoderNames().front());
  absl::StatusOr<std::unique_ptr<Encoder>> scan =
      NewEncoderByName("scanring-r32-d32");
  ASSERT_TRUE(image.ok() && scan.ok());
  absl::StatusOr<std::vector<float>> code =
      (*image)->Encode(Scan(std::vector<float>(180, 3.0f)));
  EXPECT_EQ(code.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(code.status().message(), HasSubstr("holds no image"));
  code = (*scan)->Encode(Image());
  EXPECT_EQ(code.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(code.status().message(), HasSubstr("holds no laser scan"));
}

TEST(ScanRingEncoderTest, IsInvariantToTurningTheScanAround) {
  // A 360-degree scan rotated by whole beams (and mirrored) has the same
  // ring histogram and the same pairwise distances.
  std::vector<float> ranges(360);
  for (size_t i = 0; i < ranges.size(); ++i) {
    ranges[i] = 2.0f + 1.5f * std::sin(i * 0.07f) + (i % 17) * 0.1f;
  }
  Observation a = Scan(ranges);
  a.scan.field_of_view = 2.0 * M_PI * 359.0 / 360.0;
  Observation b = a;
  std::rotate(b.scan.ranges.begin(), b.scan.ranges.begin() + 97,
              b.scan.ranges.end());
  Observation c = a;
  std::reverse(c.scan.ranges.begin(), c.scan.ranges.end());
  std::unique_ptr<Encoder> encoder = NewScanRingEncoder({});
  absl::StatusOr<std::vector<float>> code_a = encoder->Encode(a);
  absl::StatusOr<std::vector<float>> code_b = encoder->Encode(b);
  absl::StatusOr<std::vector<float>> code_c = encoder->Encode(c);
  ASSERT_TRUE(code_a.ok() && code_b.ok() && code_c.ok());
  for (size_t i = 0; i < code_a->size(); ++i) {
    EXPECT_NEAR((*code_a)[i], (*code_b)[i], 2e-3) << i;
    EXPECT_NEAR((*code_a)[i], (*code_c)[i], 2e-3) << i;
  }
}

TEST(ScanRingEncoderTest, HistogramsAreShares) {
  std::unique_ptr<Encoder> encoder = NewScanRingEncoder(
      {.range_bins = 4, .distance_bins = 4, .histogram_range_m = 8.0});
  // Beams: 1 m, 3 m, 100 m (beyond max_range 50: no return), 0 (none).
  absl::StatusOr<std::vector<float>> code =
      encoder->Encode(Scan({1.0f, 3.0f, 100.0f, 0.0f}));
  ASSERT_TRUE(code.ok()) << code.status();
  ASSERT_EQ(code->size(), 9u);
  EXPECT_FLOAT_EQ((*code)[0], 0.25f);  // 1 m in ring [0, 2)
  EXPECT_FLOAT_EQ((*code)[1], 0.25f);  // 3 m in ring [2, 4)
  EXPECT_FLOAT_EQ((*code)[4], 0.5f);   // no return
  float pairs = 0.0f;
  for (size_t i = 5; i < 9; ++i) pairs += (*code)[i];
  EXPECT_FLOAT_EQ(pairs, 1.0f);
}

TEST(ScanRingEncoderTest, PerturbRotatesByWholeBeams) {
  std::unique_ptr<Encoder> encoder =
      NewScanRingEncoder({.max_rotation_beams = 0});
  std::mt19937_64 rng(1);
  const Observation scan = Scan({1, 2, 3, 4, 5});
  absl::StatusOr<Observation> same = encoder->Perturb(scan, rng);
  ASSERT_TRUE(same.ok());
  EXPECT_EQ(same->scan.ranges, scan.scan.ranges);
  encoder = NewScanRingEncoder({.max_rotation_beams = 2});
  for (int i = 0; i < 20; ++i) {
    absl::StatusOr<Observation> moved = encoder->Perturb(scan, rng);
    ASSERT_TRUE(moved.ok());
    int zeros = static_cast<int>(
        std::count(moved->scan.ranges.begin(), moved->scan.ranges.end(), 0.0f));
    EXPECT_LE(zeros, 2);
  }
  EXPECT_EQ(NewScanRingEncoder({.range_bins = 0}), nullptr);
}

TEST(ScanRingEncoderTest, SeparatesPlacesOfTheRealAcesLog) {
  // Scans taken at the same spot are nearer in code than scans far apart:
  // the code carries place information on real data.
  absl::StatusOr<std::string> text =
      ReadMaybeBzip2(std::string(FLEETMEM_DATA_DIR) + "/laser/aces.clf.bz2");
  ASSERT_TRUE(text.ok()) << text.status();
  absl::StatusOr<std::vector<Observation>> scans =
      ParseCarmenLog(*text, "aces");
  ASSERT_TRUE(scans.ok());
  std::unique_ptr<Encoder> encoder = NewScanRingEncoder({});
  auto distance = [&](size_t i, size_t j) {
    std::vector<float> a = *encoder->Encode((*scans)[i]);
    std::vector<float> b = *encoder->Encode((*scans)[j]);
    double sum = 0.0;
    for (size_t k = 0; k < a.size(); ++k) sum += (a[k] - b[k]) * (a[k] - b[k]);
    return std::sqrt(sum);
  };
  int nearer = 0, trials = 0;
  for (size_t i = 100; i + 2000 < scans->size(); i += 250) {
    ++trials;
    nearer += distance(i, i + 1) < distance(i, i + 2000) ? 1 : 0;
  }
  EXPECT_GE(nearer, trials * 8 / 10) << nearer << " of " << trials;
}

}  // namespace
}  // namespace fleetmem::robot
