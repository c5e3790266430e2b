#include "clients/robot/learning/triplets.h"

#include <random>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::robot::gpl {
namespace {

// Places along a line every 10 units; domain 0 then domain 1 at the same
// places (summer and winter frames of one route).
std::vector<TripletSample> Route(int n) {
  std::vector<TripletSample> pool;
  for (int d = 0; d < 2; ++d) {
    for (int i = 0; i < n; ++i) pool.push_back({{10.0 * i, 0, 0, 0}, d});
  }
  return pool;
}

TEST(TripletsTest, PositivesPreferTheOtherDomainAndNegativesAreFar) {
  const auto pool = Route(30);
  std::mt19937_64 rng(1);
  std::vector<size_t> anchors{35, 40, 5};
  TripletMiningOptions options;  // +-20 positives, > 100 negatives
  auto triplets = MineTriplets(pool, anchors, {}, options, rng);
  ASSERT_EQ(triplets.size(), 3u);
  for (const TripletIndex& t : triplets) {
    EXPECT_NE(pool[t.positive].domain, pool[t.anchor].domain);
    EXPECT_LE(std::abs(pool[t.positive].place.x - pool[t.anchor].place.x),
              20.0);
    EXPECT_GT(std::abs(pool[t.negative].place.x - pool[t.anchor].place.x),
              100.0);
  }
  options.prefer_other_domain = false;
  const auto summer =
      std::vector<TripletSample>(pool.begin(), pool.begin() + 30);
  auto same = MineTriplets(summer, std::vector<size_t>{5}, {}, options, rng);
  ASSERT_EQ(same.size(), 1u);
  EXPECT_NE(same[0].positive, 5u);
}

TEST(TripletsTest, AnchorsWithoutPositiveOrNegativeAreLeftOut) {
  std::vector<TripletSample> pool{{{0, 0, 0, 0}, 0}, {{500, 0, 0, 0}, 0}};
  std::mt19937_64 rng(1);
  EXPECT_TRUE(
      MineTriplets(pool, std::vector<size_t>{0, 1}, {}, {}, rng).empty());
  std::vector<TripletSample> near{{{0, 0, 0, 0}, 0}, {{10, 0, 0, 0}, 0}};
  EXPECT_TRUE(MineTriplets(near, std::vector<size_t>{0}, {}, {}, rng).empty());
}

TEST(TripletsTest, MiningTakesTheNearestNegativeCandidate) {
  const auto pool = Route(30);
  std::vector<std::vector<float>> descriptors(pool.size(), {1.0f, 0.0f});
  descriptors[29] = {0.0f, 1.0f};  // anchor 0's look-alike far away: x = 290
  descriptors[0] = {0.0f, 1.0f};
  TripletMiningOptions options;
  options.negative_candidates = 400;  // sees every candidate
  std::mt19937_64 rng(3);
  auto t =
      MineTriplets(pool, std::vector<size_t>{0}, descriptors, options, rng);
  ASSERT_EQ(t.size(), 1u);
  EXPECT_EQ(t[0].negative, 29u);
}

TEST(TripletsTest, HardestTripletsTakeFarthestPositiveAndNearestNegative) {
  const auto pool = Route(30);
  std::vector<std::vector<float>> descriptors(pool.size(), {1.0f, 0.0f});
  descriptors[32] = {-1.0f, 0.0f};  // winter frame at x = 20: far in F
  descriptors[15] = {0.9f, 0.1f};
  descriptors[20] = {1.0f, 0.0f};
  auto t = HardestTriplets(pool, std::vector<size_t>{0}, descriptors, {});
  ASSERT_EQ(t.size(), 1u);
  EXPECT_EQ(t[0].positive, 32u);
  // Nearest negative: every far sample is at distance 0 except 15; the
  // first of the ties (x = 110, index 11) is taken.
  EXPECT_EQ(t[0].negative, 11u);
  // No positive: the anchor is its own positive.
  std::vector<TripletSample> lone{{{0, 0, 0, 0}, 0}, {{500, 0, 0, 0}, 0}};
  std::vector<std::vector<float>> two{{1.0f, 0.0f}, {0.0f, 1.0f}};
  auto own = HardestTriplets(lone, std::vector<size_t>{0}, two, {});
  ASSERT_EQ(own.size(), 1u);
  EXPECT_EQ(own[0].positive, 0u);
  EXPECT_EQ(own[0].negative, 1u);
}

}  // namespace
}  // namespace fleetmem::robot::gpl
