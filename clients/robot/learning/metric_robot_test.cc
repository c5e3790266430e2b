#include "clients/robot/learning/metric_robot.h"

#include <random>
#include <string>
#include <vector>

#include "clients/robot/sensing/encoder_factory.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/core.hpp"
#include "opencv2/imgproc.hpp"
#include "services/common/files.h"

namespace fleetmem::robot::gpl {
namespace {

// A 64 x 32 grey frame of random blocks per place; the other season is
// brighter and noisier.
cv::Mat Frame(uint64_t place, bool winter) {
  std::mt19937_64 rng(place);
  cv::Mat blocks(4, 8, CV_8UC1);
  for (int r = 0; r < blocks.rows; ++r)
    for (int c = 0; c < blocks.cols; ++c)
      blocks.at<uint8_t>(r, c) = uint8_t(rng() % 200);
  cv::Mat image;
  cv::resize(blocks, image, cv::Size(64, 32), 0, 0, cv::INTER_NEAREST);
  if (winter) {
    cv::Mat noise(32, 64, CV_8UC1);
    cv::randu(noise, 0, 60);
    image = image * 0.6 + 90 + noise;
  }
  return image;
}

class MetricRobotTest : public testing::Test {
 protected:
  void SetUp() override {
    auto hog = NewEncoderByName("hog-64x32-c8-s8-b6");
    ASSERT_TRUE(hog.ok()) << hog.status();
    encoder_ = *std::move(hog);
    auto dir = files::MakeTempDir("fleetmem-metric-robot-");
    ASSERT_TRUE(dir.ok());
    dir_ = *dir;
  }
  void TearDown() override { (void)files::RemoveTree(dir_); }

  std::unique_ptr<Encoder> encoder_;
  std::string dir_;
};

TEST_F(MetricRobotTest, LearnsFromRememberedPlacesAndResumesFromItsFile) {
  const std::string path = dir_ + "/metric-head.bin";
  const int dim = int(encoder_->dimension());
  auto head = MetricRobotLearner::LoadOrNew(path, dim, {});
  ASSERT_TRUE(head.ok()) << head.status();
  EXPECT_FALSE(head->fitted());
  MetricRobotLearner learner(*std::move(head), path);
  std::vector<core::MemoryTrace> segment, memory;
  std::vector<std::vector<float>> codes;
  for (int i = 0; i < 20; ++i) {
    Observation o;
    o.place.x = 50.0 * i;
    o.image = Frame(100 + i, true);
    core::MemoryTrace& w = segment.emplace_back();
    w.code = *encoder_->Encode(o);
    w.place = o.place;
    w.domain = "winter";
    codes.push_back(w.code);
    Observation s = o;
    s.image = Frame(100 + i, false);
    core::MemoryTrace& t = memory.emplace_back();
    t.code = *encoder_->Encode(s);
    t.place = s.place;
    t.domain = "summer";
  }
  // A trace of another encoder is left out, not misread.
  core::MemoryTrace foreign = memory[0];
  foreign.code.resize(7);
  memory.push_back(foreign);
  auto report = learner.Learn(segment, {}, {}, memory);
  ASSERT_TRUE(report.ok()) << report.status();
  EXPECT_EQ(*report, "40 samples, 40 pairs (40 across domains)");
  EXPECT_EQ(learner.last().samples, 40u);
  EXPECT_EQ(learner.last().cross_domain_pairs, 40u);  // each with its partner
  auto rewards = learner.ExternalRewards(segment, memory);
  ASSERT_TRUE(rewards.ok()) << rewards.status();
  EXPECT_EQ(rewards->size(), 20u);
  // A restart reads the saved head: the same descriptors.
  auto again = MetricRobotLearner::LoadOrNew(path, dim, {});
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->fitted());
  auto before = learner.Describe(codes);
  auto after = again->Describe(codes);
  ASSERT_TRUE(before.ok() && after.ok());
  for (size_t i = 0; i < codes.size(); ++i) {
    for (size_t c = 0; c < (*before)[i].size(); ++c)
      EXPECT_NEAR((*before)[i][c], (*after)[i][c], 1e-5);
  }
  // A head made for another code is refused, not misused.
  EXPECT_EQ(MetricRobotLearner::LoadOrNew(path, dim + 1, {}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(MetricRobotTest, AnUnreadableHeadFileIsDataLoss) {
  const std::string path = dir_ + "/metric-head.bin";
  ASSERT_TRUE(files::WriteFile(path, "not a head").ok());
  EXPECT_EQ(MetricRobotLearner::LoadOrNew(path, 504, {}).status().code(),
            absl::StatusCode::kDataLoss);
  // Truncated: a fitted head's bytes cut short.
  MetricHead head(3, {});
  std::vector<LearnSample> samples{{{1, 0, 0}, {0, 0, 0, 0}, 0},
                                   {{0, 1, 0}, {5, 0, 0, 0}, 1},
                                   {{0, 0, 1}, {100, 0, 0, 0}, 0}};
  ASSERT_TRUE(head.Learn(samples).ok());
  const std::string bytes = head.Serialize();
  EXPECT_TRUE(MetricHead::Deserialize(bytes, 3).ok());
  EXPECT_EQ(MetricHead::Deserialize(bytes.substr(0, bytes.size() - 8), 3)
                .status()
                .code(),
            absl::StatusCode::kDataLoss);
  EXPECT_EQ(MetricHead::Deserialize(bytes + "x", 3).status().code(),
            absl::StatusCode::kDataLoss);
}

}  // namespace
}  // namespace fleetmem::robot::gpl
