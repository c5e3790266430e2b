#include "clients/robot/runtime/segment_step.h"

#include <cmath>
#include <random>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::robot {
namespace {

using ::testing::ElementsAre;

core::MemoryTrace Trace(std::string robot, uint64_t seq, double x,
                        std::vector<float> code, float r_in = 0.0f) {
  core::MemoryTrace t;
  t.robot_id = std::move(robot);
  t.seq = seq;
  t.domain = "winter";
  t.place.x = x;
  t.code = std::move(code);
  t.reward_internal = r_in;
  t.reward = 1.0f;
  return t;
}

// Records what it is given; R_ex = 0.5 for every trace.
class FixedLearner : public Learner {
 public:
  absl::StatusOr<std::string> Learn(
      std::span<const core::MemoryTrace> segment,
      std::span<const Observation> observations,
      std::span<const core::MemoryTrace> replayed,
      std::span<const core::MemoryTrace> memory) override {
    segment_size = segment.size();
    observations_size = observations.size();
    replayed_size = replayed.size();
    for (const core::MemoryTrace& t : memory)
      remembered.push_back(t.robot_id + ":" + std::to_string(t.seq));
    return std::string("fixed");
  }
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const core::MemoryTrace> segment,
      std::span<const core::MemoryTrace>) override {
    return std::vector<float>(segment.size(), 0.5f);
  }
  size_t segment_size = 0, observations_size = 0, replayed_size = 0;
  std::vector<std::string> remembered;
};

class SegmentStepTest : public ::testing::Test {
 protected:
  SegmentStepTest() : memory_("robot-a", DynamicMemoryOptions{}) {
    // M_D: two own traces and one of a peer.
    memory_.AddOwn(Trace("robot-a", 1, 0, {1, 0}));
    memory_.AddOwn(Trace("robot-a", 2, 10, {0, 1}));
    memory_.Refresh({Trace("robot-b", 7, 20, {1, 1})});
  }
  std::vector<core::MemoryTrace> Segment() const {
    return {Trace("robot-a", 0, 100, {1, 0}, 0.25f),
            Trace("robot-a", 0, 110, {0, 1}, 0.5f)};
  }
  DynamicMemory memory_;
  std::mt19937_64 rng_{1};
};

TEST_F(SegmentStepTest, RewardsFollowTheModeAndTheLearner) {
  const float r_in[2] = {0.25f, 0.5f};
  const std::pair<RewardMode, std::vector<float>> cases[] = {
      {RewardMode::kFull, {0.75f, 1.0f}},
      {RewardMode::kNoExternal, {r_in[0], r_in[1]}},
      {RewardMode::kNoInternal, {0.5f, 0.5f}},
      {RewardMode::kUniform, {1.0f, 1.0f}},
  };
  for (const auto& [mode, expected] : cases) {
    FixedLearner learner;
    SegmentStepOptions options;
    options.rewards = mode;
    absl::StatusOr<SegmentStepResult> step = RunSegmentStep(
        options, Segment(), {}, memory_, rng_, &learner, nullptr);
    ASSERT_TRUE(step.ok()) << step.status();
    ASSERT_EQ(step->traces.size(), 2u);
    for (size_t k = 0; k < 2; ++k) {
      EXPECT_FLOAT_EQ(step->traces[k].reward_external, 0.5f);
      EXPECT_FLOAT_EQ(step->traces[k].reward, expected[k]);
      EXPECT_FLOAT_EQ(step->traces[k].reward_internal, r_in[k]);
    }
    EXPECT_EQ(step->report, "fixed");
    EXPECT_EQ(learner.segment_size, 2u);
  }
}

// R_ex = the number of traces it is scored against, so that a test sees
// what the re-scoring compared the robot's remembered traces with.
class CountingLearner : public FixedLearner {
 public:
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const core::MemoryTrace> segment,
      std::span<const core::MemoryTrace> memory) override {
    return std::vector<float>(segment.size(), float(memory.size()));
  }
};

TEST_F(SegmentStepTest, RescoringGivesTheOwnRememberedTracesNewRewards) {
  CountingLearner learner;
  SegmentStepOptions options;
  options.rescore_remembered = true;
  absl::StatusOr<SegmentStepResult> step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &learner, nullptr);
  ASSERT_TRUE(step.ok()) << step.status();
  // robot-a's two traces of M_D, scored against the peer's one trace (not
  // against themselves); R = R_ex + R_in; the peer's trace is not theirs.
  ASSERT_EQ(step->rescored.size(), 2u);
  for (const core::MemoryTrace& t : step->rescored) {
    EXPECT_EQ(t.robot_id, "robot-a");
    EXPECT_FLOAT_EQ(t.reward_external, 1.0f);
    EXPECT_FLOAT_EQ(t.reward, 1.0f + t.reward_internal);
  }
  // Off by default, and off for the ablations' reward modes.
  options.rescore_remembered = false;
  step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &learner, nullptr);
  ASSERT_TRUE(step.ok());
  EXPECT_TRUE(step->rescored.empty());
  options.rescore_remembered = true;
  options.rewards = RewardMode::kUniform;
  step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &learner, nullptr);
  ASSERT_TRUE(step.ok());
  EXPECT_TRUE(step->rescored.empty());
  // Unchanged rewards are not sent again: R_ex already 1.
  std::vector<core::MemoryTrace> own;
  for (const ReplayEntry& e : memory_.entries()) {
    if (e.trace.robot_id == "robot-a") own.push_back(e.trace);
  }
  for (core::MemoryTrace& t : own) {
    t.reward_external = 1.0f;
    memory_.AddOwn(t);  // replaces the entry of its (robot, seq)
  }
  options.rewards = RewardMode::kFull;
  step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &learner, nullptr);
  ASSERT_TRUE(step.ok());
  EXPECT_TRUE(step->rescored.empty());
}

TEST_F(SegmentStepTest, ReplayCountsOwnAndPeerTraces) {
  FixedLearner learner;
  SegmentStepOptions options;
  options.replay_per_segment = 64;  // more than M_D holds: all three
  absl::StatusOr<SegmentStepResult> step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &learner, nullptr);
  ASSERT_TRUE(step.ok());
  EXPECT_EQ(step->replayed_own, 2u);
  EXPECT_EQ(step->replayed_peer, 1u);
  EXPECT_EQ(learner.replayed_size, 3u);
  // M_D as it holds them (the refreshed peer's first), then nothing recalled.
  EXPECT_THAT(learner.remembered,
              ElementsAre("robot-b:7", "robot-a:1", "robot-a:2"));
  // Replay counted the draws in M_D (n of Eq. 19).
  for (const ReplayEntry& e : memory_.entries()) EXPECT_EQ(e.local_replays, 1u);
}

TEST_F(SegmentStepTest, RecalledTracesJoinTheMemoryOnceEach) {
  FixedLearner learner;
  SegmentStepOptions options;
  options.recall_per_observation = 2;
  std::vector<double> asked;
  const PlaceRecall recall =
      [&](const core::MemoryTrace& observed,
          size_t k) -> absl::StatusOr<std::vector<core::MemoryTrace>> {
    EXPECT_EQ(k, 2u);
    asked.push_back(observed.place.x);
    // Both observations recall robot-c:5; each one more of its own.
    return std::vector<core::MemoryTrace>{
        Trace("robot-c", 5, observed.place.x, {1, 0}),
        Trace("robot-c", uint64_t(observed.place.x), observed.place.x, {0, 1})};
  };
  absl::StatusOr<SegmentStepResult> step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &learner, recall);
  ASSERT_TRUE(step.ok());
  EXPECT_THAT(asked, ElementsAre(100, 110));
  EXPECT_EQ(step->recalled, 3u);
  EXPECT_THAT(learner.remembered,
              ElementsAre("robot-b:7", "robot-a:1", "robot-a:2", "robot-c:5",
                          "robot-c:100", "robot-c:110"));
}

TEST_F(SegmentStepTest, NotFoundStopsRecallAndOtherErrorsStopTheStep) {
  FixedLearner learner;
  SegmentStepOptions options;
  int calls = 0;
  const PlaceRecall empty_fleet =
      [&](const core::MemoryTrace&,
          size_t) -> absl::StatusOr<std::vector<core::MemoryTrace>> {
    ++calls;
    return absl::NotFoundError("no fleet");
  };
  absl::StatusOr<SegmentStepResult> step = RunSegmentStep(
      options, Segment(), {}, memory_, rng_, &learner, empty_fleet);
  ASSERT_TRUE(step.ok());
  EXPECT_EQ(calls, 1);
  EXPECT_EQ(step->recalled, 0u);

  FixedLearner untouched;
  const PlaceRecall broken =
      [](const core::MemoryTrace&,
         size_t) -> absl::StatusOr<std::vector<core::MemoryTrace>> {
    return absl::PermissionDeniedError("token revoked");
  };
  step =
      RunSegmentStep(options, Segment(), {}, memory_, rng_, &untouched, broken);
  EXPECT_EQ(step.status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(untouched.segment_size, 0u);  // nothing learned after it
}

TEST_F(SegmentStepTest, WithoutALearnerRexIsTheTripletLossInCodeSpace) {
  SegmentStepOptions options;
  options.triplet.margin = 0.1;
  options.triplet.positive_radius = 10.0;
  options.triplet.negative_radius = 50.0;
  // A and B are 5 apart (positives), C is far from both (a negative) and
  // looks like A. d between unit codes: A-B sqrt(2), A-C 0, B-C sqrt(2).
  //   A: max(0, sqrt(2) - 0 + 0.1) = sqrt(2) + 0.1
  //   B: max(0, sqrt(2) - sqrt(2) + 0.1) = 0.1
  //   C: no positive (0), nearest negative A at 0: 0.1
  std::vector<core::MemoryTrace> segment = {
      Trace("robot-a", 0, 100, {1, 0}, 0.5f),
      Trace("robot-a", 0, 105, {0, 3}, 0.5f),
      Trace("robot-a", 0, 200, {2, 0}, 0.5f)};
  absl::StatusOr<SegmentStepResult> step =
      RunSegmentStep(options, segment, {}, memory_, rng_, nullptr, nullptr);
  ASSERT_TRUE(step.ok());
  ASSERT_EQ(step->traces.size(), 3u);
  const float expected[3] = {float(std::sqrt(2.0) + 0.1), 0.1f, 0.1f};
  for (size_t k = 0; k < 3; ++k) {
    EXPECT_NEAR(step->traces[k].reward_external, expected[k], 1e-5);
    EXPECT_NEAR(step->traces[k].reward, expected[k] + 0.5f, 1e-5);
  }
  EXPECT_TRUE(step->report.empty());
}

}  // namespace
}  // namespace fleetmem::robot

namespace fleetmem::robot {
namespace {

// The warm start learns from all of M_D, with no segment, once it holds two
// domains; with one it refuses and the learner is not called.
TEST(WarmStartTest, LearnsFromTheWholeMemoryOnceItHoldsTwoDomains) {
  DynamicMemory memory("robot-c", DynamicMemoryOptions{});
  FixedLearner learner;
  EXPECT_TRUE(absl::IsFailedPrecondition(WarmStart(learner, memory).status()));
  memory.Refresh(
      {Trace("robot-a", 1, 0, {1, 0}), Trace("robot-a", 2, 10, {0, 1})});
  EXPECT_EQ(DomainCount(memory), 1u);
  EXPECT_TRUE(absl::IsFailedPrecondition(WarmStart(learner, memory).status()));
  EXPECT_TRUE(learner.remembered.empty());
  core::MemoryTrace summer = Trace("robot-b", 3, 0, {1, 1});
  summer.domain = "summer";
  memory.Refresh({Trace("robot-a", 1, 0, {1, 0}),
                  Trace("robot-a", 2, 10, {0, 1}), summer});
  EXPECT_EQ(DomainCount(memory), 2u);
  absl::StatusOr<std::string> warmed = WarmStart(learner, memory);
  ASSERT_TRUE(warmed.ok()) << warmed.status();
  EXPECT_EQ(*warmed, "fixed");
  EXPECT_EQ(learner.segment_size, 0u);
  EXPECT_EQ(learner.replayed_size, 0u);
  EXPECT_EQ(learner.remembered.size(), memory.size());
}

}  // namespace
}  // namespace fleetmem::robot
