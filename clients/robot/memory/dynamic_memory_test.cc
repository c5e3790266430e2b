#include "clients/robot/memory/dynamic_memory.h"

#include <cmath>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::robot {
namespace {

using ::testing::ElementsAre;
using ::testing::Pair;

core::MemoryTrace Trace(const std::string& robot, uint64_t seq, float reward) {
  core::MemoryTrace trace;
  trace.robot_id = robot;
  trace.seq = seq;
  trace.reward = reward;
  trace.code = {1.0f, 0.0f};
  return trace;
}

TEST(DynamicMemoryTest, StaysWithinItsCapacityKeepingTheHighestWeights) {
  DynamicMemory memory("r1", {.capacity = 5});
  for (uint64_t seq = 1; seq <= 10; ++seq) {
    memory.AddOwn(Trace("r1", seq, static_cast<float>(seq)));
    EXPECT_LE(memory.size(), 5u);
  }
  std::vector<uint64_t> kept;
  for (const ReplayEntry& entry : memory.entries()) {
    kept.push_back(entry.trace.seq);
  }
  EXPECT_THAT(kept, ElementsAre(6, 7, 8, 9, 10));
}

TEST(DynamicMemoryTest, WeightIsGammaToTheLocalReplaysTimesReward) {
  DynamicMemory memory("r1", {.capacity = 10, .gamma = 0.5});
  memory.AddOwn(Trace("r1", 1, 2.0f));
  memory.AddOwn(Trace("r1", 2, 0.0f));  // clamped to the floor
  EXPECT_DOUBLE_EQ(memory.Weight(memory.entries()[0]), 2.0);
  EXPECT_DOUBLE_EQ(memory.Weight(memory.entries()[1]), 1e-3);
  std::mt19937_64 rng(1);
  for (int n = 1; n <= 3; ++n) {
    // The positive-weight trace is drawn first every time.
    const std::vector<core::MemoryTrace> drawn = memory.Replay(1, rng);
    ASSERT_EQ(drawn.size(), 1u);
    EXPECT_EQ(drawn[0].seq, 1u);
    EXPECT_EQ(memory.entries()[0].local_replays, static_cast<uint32_t>(n));
    EXPECT_DOUBLE_EQ(memory.Weight(memory.entries()[0]),
                     2.0 * std::pow(0.5, n));
  }
}

TEST(DynamicMemoryTest, SetRewardsKeepsTheEntrysPlaceAndReplayCount) {
  DynamicMemory memory("r1", {.capacity = 10, .gamma = 0.5});
  memory.AddOwn(Trace("r1", 1, 2.0f));
  memory.AddOwn(Trace("r1", 2, 1.0f));
  std::mt19937_64 rng(1);
  ASSERT_EQ(memory.Replay(1, rng)[0].seq, 1u);
  core::MemoryTrace rescored = Trace("r1", 1, 4.0f);
  rescored.reward_external = 3.0f;
  rescored.reward_internal = 1.0f;
  EXPECT_TRUE(memory.SetRewards(rescored));
  EXPECT_EQ(memory.entries()[0].trace.seq, 1u);  // still first
  EXPECT_EQ(memory.entries()[0].local_replays, 1u);
  EXPECT_FLOAT_EQ(memory.entries()[0].trace.reward_external, 3.0f);
  EXPECT_DOUBLE_EQ(memory.Weight(memory.entries()[0]), 4.0 * 0.5);
  EXPECT_FALSE(memory.SetRewards(Trace("r1", 9, 1.0f)));
  EXPECT_EQ(memory.size(), 2u);
}

TEST(DynamicMemoryTest, TimeDecayShiftsReplayToLessReplayedTraces) {
  // Two traces of equal reward; after A was replayed 10 times (gamma 0.5),
  // B is drawn first almost always.
  DynamicMemory memory("r1", {.capacity = 10, .gamma = 0.5});
  memory.AddOwn(Trace("r1", 1, 1.0f));
  std::mt19937_64 rng(7);
  for (int i = 0; i < 10; ++i) memory.Replay(1, rng);
  memory.AddOwn(Trace("r1", 2, 1.0f));
  int first_is_2 = 0;
  for (int i = 0; i < 200; ++i) {
    std::mt19937_64 trial(100 + i);
    DynamicMemory copy = memory;
    first_is_2 += copy.Replay(1, trial)[0].seq == 2 ? 1 : 0;
  }
  // P = 1 / (1 + 0.5^10) = 0.999; without decay it would be 0.5.
  EXPECT_GT(first_is_2, 190);
}

TEST(DynamicMemoryTest, RefreshReplacesFleetTracesAndKeepsUnsentOwnOnes) {
  DynamicMemory memory("r1", {.capacity = 10});
  memory.AddOwn(Trace("r1", 1, 1.0f));
  memory.AddOwn(Trace("r1", 2, 1.0f));
  memory.Refresh({Trace("r2", 1, 1.0f), Trace("r1", 1, 1.0f)});
  std::mt19937_64 rng(3);
  memory.Replay(3, rng);  // every entry once
  EXPECT_THAT(memory.CountByRobot(), ElementsAre(Pair("r1", 2), Pair("r2", 1)));
  // A second refresh drops r2's trace, keeps r1 #2 (still local) and the
  // local replay count of r1 #1, which the fleet hands out again.
  memory.Refresh({Trace("r3", 5, 1.0f), Trace("r1", 1, 1.0f)});
  EXPECT_THAT(memory.CountByRobot(), ElementsAre(Pair("r1", 2), Pair("r3", 1)));
  for (const ReplayEntry& entry : memory.entries()) {
    if (entry.trace.robot_id == "r1" && entry.trace.seq == 1) {
      EXPECT_EQ(entry.local_replays, 1u);
      EXPECT_FALSE(entry.local);
    }
    if (entry.trace.robot_id == "r3") EXPECT_EQ(entry.local_replays, 0u);
  }
}

TEST(DynamicMemoryTest, RefreshHonoursTheBound) {
  DynamicMemory memory("r1", {.capacity = 3});
  std::vector<core::MemoryTrace> sample;
  for (uint64_t seq = 1; seq <= 5; ++seq) {
    sample.push_back(Trace("r2", seq, static_cast<float>(seq)));
  }
  memory.Refresh(sample);
  EXPECT_EQ(memory.size(), 3u);
  std::mt19937_64 rng(1);
  EXPECT_EQ(memory.Replay(10, rng).size(), 3u);
}

}  // namespace
}  // namespace fleetmem::robot
