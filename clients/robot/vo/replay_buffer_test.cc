#include "clients/robot/vo/replay_buffer.h"

#include <cmath>
#include <set>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::vo {
namespace {

Triplet Tagged(int tag) {
  Triplet t;
  t.distances_m = {double(tag), 0.0};
  return t;
}

// A unit feature at `degrees` in the plane of the first two axes.
std::vector<float> At(double degrees) {
  const double r = degrees * M_PI / 180.0;
  return {float(std::cos(r)), float(std::sin(r)), 0.0f};
}

TEST(ReplayBuffer, AdmitsOnlyBelowTheSimilarityThreshold) {
  ReplayBuffer buffer({.capacity = 10, .max_similarity = 0.95});
  EXPECT_EQ(buffer.Offer(At(0), Tagged(0)), ReplayBuffer::Outcome::kAdmitted);
  // cos(15 deg) = 0.966 >= 0.95: refused.
  EXPECT_EQ(buffer.Offer(At(15), Tagged(1)),
            ReplayBuffer::Outcome::kTooSimilar);
  // cos(20 deg) = 0.940 < 0.95: admitted.
  EXPECT_EQ(buffer.Offer(At(20), Tagged(2)), ReplayBuffer::Outcome::kAdmitted);
  // Scale does not matter (cosine), the sign does.
  std::vector<float> scaled = At(0);
  for (float& v : scaled) v *= 7.0f;
  EXPECT_EQ(buffer.Offer(scaled, Tagged(3)),
            ReplayBuffer::Outcome::kTooSimilar);
  EXPECT_EQ(buffer.Offer(At(180), Tagged(4)), ReplayBuffer::Outcome::kAdmitted);
  EXPECT_EQ(buffer.Offer(std::vector<float>{0.0f, 0.0f, 0.0f}, Tagged(5)),
            ReplayBuffer::Outcome::kTooSimilar);
  EXPECT_EQ(buffer.size(), 3u);
  EXPECT_EQ(buffer.refused(), 3u);
}

TEST(ReplayBuffer, WhenFullDropsTheLaterOfTheClosestPair) {
  ReplayBuffer buffer({.capacity = 3, .max_similarity = 0.95});
  ASSERT_EQ(buffer.Offer(At(0), Tagged(0)), ReplayBuffer::Outcome::kAdmitted);
  ASSERT_EQ(buffer.Offer(At(90), Tagged(1)), ReplayBuffer::Outcome::kAdmitted);
  ASSERT_EQ(buffer.Offer(At(180), Tagged(2)), ReplayBuffer::Outcome::kAdmitted);
  // 115 degrees is 25 from 90: ids 1 and 3 are the closest pair; 3 goes.
  EXPECT_EQ(buffer.Offer(At(115), Tagged(3)),
            ReplayBuffer::Outcome::kAdmittedWithEviction);
  EXPECT_EQ(buffer.Ids(), (std::vector<uint64_t>{0, 1, 2}));
  // 270 degrees: the closest pair is now (0, 90) and (90, 180) and (180,
  // 270) and (270, 0) at 90 degrees each; ties go to the smallest ids
  // (0, 1), and the later, 1, goes.
  EXPECT_EQ(buffer.Offer(At(270), Tagged(4)),
            ReplayBuffer::Outcome::kAdmittedWithEviction);
  EXPECT_EQ(buffer.Ids(), (std::vector<uint64_t>{0, 2, 4}));
  EXPECT_EQ(buffer.evicted(), 2u);
  EXPECT_EQ(buffer.size(), 3u);
}

TEST(ReplayMemory, DrawsOneSampleOfEveryOtherEnvironment) {
  ReplayMemory memory({.capacity = 5, .max_similarity = 0.95});
  memory.Offer("a", At(0), Tagged(10));
  memory.Offer("a", At(90), Tagged(11));
  memory.Offer("b", At(0), Tagged(20));
  memory.Offer("c", At(0), Tagged(30));
  std::mt19937_64 rng(1);
  std::vector<Triplet> drawn = memory.DrawOthers("b", rng);
  ASSERT_EQ(drawn.size(), 2u);
  EXPECT_TRUE(drawn[0].distances_m[0] == 10 || drawn[0].distances_m[0] == 11);
  EXPECT_EQ(drawn[1].distances_m[0], 30);
  EXPECT_EQ(memory.DrawOthers("z", rng).size(), 3u);
  // Both samples of "a" are drawn over many draws.
  std::set<double> seen;
  for (int i = 0; i < 50; ++i) {
    seen.insert(memory.DrawOthers("b", rng)[0].distances_m[0]);
  }
  EXPECT_EQ(seen.size(), 2u);
}

}  // namespace
}  // namespace fleetmem::vo
