#include "clients/robot/learning/gpl_robot.h"

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <random>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/core.hpp"
#include "opencv2/imgproc.hpp"

namespace fleetmem::robot::gpl {
namespace {

cv::Mat Noise(uint64_t seed) {
  cv::RNG rng(seed);
  cv::Mat m(32, 64, CV_8UC1);
  rng.fill(m, cv::RNG::UNIFORM, 0, 256);
  return m;
}

std::unique_ptr<SharedModel> SavedAndLoaded(bool wrap = false) {
  GplOptions options;
  options.wrap_horizontal = wrap;
  auto model = *GplModel::Create(options, "gpl-robot-test-v1");
  std::vector<cv::Mat> images;
  for (int i = 0; i < 16; ++i) images.push_back(Noise(500 + i));
  EXPECT_TRUE(model->InitialisePlaceHead(*model->Encode(images)).ok());
  const std::string path = ::testing::TempDir() + "/gpl-robot-" +
                           std::to_string(::getpid()) + (wrap ? "w" : "") +
                           ".pt";
  EXPECT_TRUE(model->Save(path).ok());
  auto shared = LoadSharedModel(path);
  std::remove(path.c_str());
  EXPECT_TRUE(shared.ok()) << shared.status();
  return shared.ok() ? *std::move(shared) : nullptr;
}

// A place's look: a random 4 x 8 block pattern; another season sees it
// brighter and with noise.
cv::Mat Place(uint64_t seed, bool other_season) {
  cv::RNG rng(seed);
  cv::Mat blocks(4, 8, CV_8UC1);
  rng.fill(blocks, cv::RNG::UNIFORM, 0, 200);
  cv::Mat image;
  cv::resize(blocks, image, cv::Size(64, 32), 0, 0, cv::INTER_NEAREST);
  if (!other_season) return image;
  cv::Mat noise(32, 64, CV_8UC1);
  cv::RNG(seed + 1000).fill(noise, cv::RNG::UNIFORM, 0, 60);
  return image + noise;
}

TEST(GplRobotTest, RollColumnsRotatesAboutTheVerticalAxis) {
  cv::Mat m = (cv::Mat_<uint8_t>(1, 4) << 1, 2, 3, 4);
  cv::Mat r = RollColumns(m, 1);
  EXPECT_EQ(r.at<uint8_t>(0, 0), 4);
  EXPECT_EQ(r.at<uint8_t>(0, 1), 1);
  EXPECT_EQ(RollColumns(m, -1).at<uint8_t>(0, 0), 2);
  EXPECT_EQ(RollColumns(m, 4).at<uint8_t>(0, 2), 3);
}

TEST(GplRobotTest, EncoderCarriesTheModelVersionAndFreezesIt) {
  auto shared = SavedAndLoaded();
  ASSERT_NE(shared, nullptr);
  GplEncoder encoder(shared.get());
  EXPECT_EQ(encoder.version(), "gpl-robot-test-v1");
  EXPECT_EQ(encoder.dimension(), 256u);
  Observation o;
  o.image = Noise(1);
  auto z = encoder.Encode(o);
  ASSERT_TRUE(z.ok()) << z.status();
  EXPECT_EQ(z->size(), 256u);
  Observation scan;
  scan.name = "aces.clf:3";
  scan.scan.ranges = {1.0f, 2.0f};
  EXPECT_EQ(encoder.Encode(scan).status().code(),
            absl::StatusCode::kInvalidArgument);
  std::mt19937_64 rng(1);
  auto moved = encoder.Perturb(o, rng);
  ASSERT_TRUE(moved.ok());
  EXPECT_EQ(moved->image.size(), o.image.size());
  absl::MutexLock lock(&shared->mu);
  EXPECT_TRUE(shared->model->encoder_frozen());
}

// The learner pairs a new-domain observation with the remembered trace of
// the same place: after a few segments, winter frames describe closer to
// the summer frames of their places than to other places.
TEST(GplRobotTest, LearnerPairsNewObservationsWithRememberedPlaces) {
  auto shared = SavedAndLoaded();
  ASSERT_NE(shared, nullptr);
  GplEncoder encoder(shared.get());
  SegmentLearnerOptions options;
  options.steps_per_segment = 40;
  options.batch_size = 16;
  options.generative_steps_per_segment = 1;
  GplLearner learner(shared.get(), options);
  // 12 places, 10 units apart... spread so that negatives exist.
  std::vector<Observation> winter;
  std::vector<core::MemoryTrace> segment, memory;
  for (int i = 0; i < 12; ++i) {
    Observation o;
    o.place.x = 50.0 * i;
    o.image = Place(100 + i, false);
    winter.push_back(o);
    core::MemoryTrace& w = segment.emplace_back();
    w.code = *encoder.Encode(o);
    w.place = o.place;
    w.domain = "winter";
    Observation s = o;
    s.image = Place(100 + i, true);  // another season's look
    core::MemoryTrace& t = memory.emplace_back();
    t.code = *encoder.Encode(s);
    t.place = s.place;
    t.domain = "summer";
    t.robot_id = "peer";
  }
  std::vector<core::MemoryTrace> replayed(memory.begin(), memory.begin() + 4);
  std::vector<std::vector<float>> codes;
  for (const core::MemoryTrace& t : segment) codes.push_back(t.code);
  auto before = learner.ExternalRewards(segment, memory);
  ASSERT_TRUE(before.ok()) << before.status();
  ASSERT_EQ(before->size(), 12u);
  for (int step = 0; step < 5; ++step) {
    auto report = learner.Learn(segment, winter, replayed, memory);
    ASSERT_TRUE(report.ok()) << report.status();
    EXPECT_NE(report->find("steps, loss"), std::string::npos) << *report;
  }
  EXPECT_GT(learner.last().steps, 0);
  auto after = learner.ExternalRewards(segment, memory);
  ASSERT_TRUE(after.ok());
  double sum_before = 0, sum_after = 0;
  for (int i = 0; i < 12; ++i) {
    sum_before += (*before)[i];
    sum_after += (*after)[i];
  }
  EXPECT_LT(sum_after, sum_before * 0.5) << sum_before << " -> " << sum_after;
  // A head that tells the places apart is not reported collapsed: its
  // descriptors spread (1 - |mean|^2 well above the threshold).
  EXPECT_GT(learner.last().descriptor_spread, 0.1f);
  EXPECT_FALSE(learner.last().collapsed);
  // Codes do not move: the encoder is frozen.
  EXPECT_EQ(*encoder.Encode(winter[0]), codes[0]);
}

// Eight frames, pairs of one place 200 apart, in two domains.
std::vector<core::MemoryTrace> PairedSegment(GplEncoder& encoder) {
  std::vector<core::MemoryTrace> segment;
  for (int i = 0; i < 8; ++i) {
    Observation o;
    o.image = Place(200 + i / 2, i % 2 == 1);
    core::MemoryTrace& t = segment.emplace_back();
    t.code = *encoder.Encode(o);
    t.place.x = 200.0 * (i / 2);
    t.domain = i % 2 ? "winter" : "summer";
  }
  return segment;
}

// Contradictory labels: two looks of one frame far apart (negatives of
// each other at code distance 0) and different frames at one place
// (positives). The triplet loss is lowest when every descriptor is the
// same: training on it collapses the head.
std::vector<core::MemoryTrace> PoisonedSegment(GplEncoder& encoder) {
  std::vector<core::MemoryTrace> segment;
  for (int copy = 0; copy < 2; ++copy) {
    for (int i = 0; i < 4; ++i) {
      Observation o;
      o.image = Place(300 + i, false);
      core::MemoryTrace& t = segment.emplace_back();
      t.code = *encoder.Encode(o);
      t.place.x = 1000.0 * copy;
      t.domain = "summer";
    }
  }
  return segment;
}

std::vector<std::vector<float>> Codes(
    const std::vector<core::MemoryTrace>& traces) {
  std::vector<std::vector<float>> codes;
  for (const core::MemoryTrace& t : traces) codes.push_back(t.code);
  return codes;
}

// A model whose head has learned the paired segment (healthy), and a
// second segment on it with the guard set at `collapse_spread`.
struct GuardRun {
  float start_spread = 0;  // the second segment's pool, before it
  SegmentLearnStats stats;
  std::string report;
};

float SpreadOf(const std::vector<std::vector<float>>& descriptors) {
  std::vector<double> mean(descriptors[0].size(), 0.0);
  for (const auto& d : descriptors)
    for (size_t c = 0; c < d.size(); ++c) mean[c] += d[c] / descriptors.size();
  double squared = 0;
  for (double m : mean) squared += m * m;
  return float(1.0 - squared);
}

GuardRun RunGuarded(float collapse_spread, bool roll_back, int steps) {
  GuardRun run;
  auto shared = SavedAndLoaded();
  EXPECT_NE(shared, nullptr);
  GplEncoder encoder(shared.get());
  SegmentLearnerOptions options;
  options.steps_per_segment = 60;
  options.batch_size = 8;
  options.mining_interval = 5;
  GplLearner first(shared.get(), options);
  EXPECT_TRUE(first.Learn(PairedSegment(encoder), {}, {}, {}).ok());
  options.steps_per_segment = steps;
  options.collapse_spread = collapse_spread;
  options.roll_back_collapse = roll_back;
  GplLearner second(shared.get(), options);
  const std::vector<core::MemoryTrace> poisoned = PoisonedSegment(encoder);
  auto start = second.Describe(Codes(poisoned));
  EXPECT_TRUE(start.ok());
  if (start.ok()) run.start_spread = SpreadOf(*start);
  auto report = second.Learn(poisoned, {}, {}, {});
  EXPECT_TRUE(report.ok()) << report.status();
  if (report.ok()) run.report = *report;
  run.stats = second.last();
  return run;
}

// The collapse guard: a head whose descriptors draw together past the
// threshold during a segment goes back to its last healthy weights and the
// segment stops there; without the guard it trains on into the collapse.
TEST(GplRobotTest, TheCollapseGuardKeepsTheLastHealthyHead) {
  const int steps = 200;
  const GuardRun unguarded = RunGuarded(0.0f, false, steps);
  const float healthy = unguarded.start_spread;
  const float collapsed = unguarded.stats.descriptor_spread;
  ASSERT_EQ(unguarded.stats.steps, steps);
  ASSERT_LT(collapsed, healthy / 4)
      << "the poisoned segment must draw the descriptors together";
  const float threshold = healthy / 2;

  const GuardRun guarded = RunGuarded(threshold, true, steps);
  EXPECT_FLOAT_EQ(guarded.start_spread, healthy);
  EXPECT_TRUE(guarded.stats.rolled_back);
  EXPECT_LT(guarded.stats.steps, steps);
  EXPECT_GE(guarded.stats.descriptor_spread, threshold);
  EXPECT_FALSE(guarded.stats.collapsed);
  EXPECT_NE(guarded.report.find("COLLAPSED, rolled back"), std::string::npos)
      << guarded.report;
}

// A head below the threshold before any healthy state was seen trains on:
// there is nothing to go back to (a fresh head of this fixture starts with
// its descriptors together).
TEST(GplRobotTest, AHeadNeverSeenHealthyTrainsOn) {
  auto shared = SavedAndLoaded();
  ASSERT_NE(shared, nullptr);
  GplEncoder encoder(shared.get());
  SegmentLearnerOptions options;
  options.steps_per_segment = 20;
  options.batch_size = 8;
  options.collapse_spread = 2.0f;  // above any spread
  GplLearner learner(shared.get(), options);
  const std::vector<core::MemoryTrace> segment = PairedSegment(encoder);
  auto before = learner.Describe(Codes(segment));
  ASSERT_TRUE(before.ok());
  ASSERT_TRUE(learner.Learn(segment, {}, {}, {}).ok());
  EXPECT_EQ(learner.last().steps, 20);
  EXPECT_TRUE(learner.last().collapsed);
  EXPECT_FALSE(learner.last().rolled_back);
  auto after = learner.Describe(Codes(segment));
  ASSERT_TRUE(after.ok());
  EXPECT_NE(*after, *before);
}

}  // namespace
}  // namespace fleetmem::robot::gpl
