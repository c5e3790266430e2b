#include "clients/robot/sensing/code_search.h"

#include <cmath>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::robot {
namespace {

using ::testing::ElementsAre;
using ::testing::FloatNear;

TEST(CosineSimilarityTest, Cases) {
  struct Case {
    std::vector<float> a, b;
    float want;
  };
  const Case cases[] = {
      {{1, 2, 3}, {1, 2, 3}, 1.0f}, {{1, 2, 3}, {2, 4, 6}, 1.0f},
      {{1, 0}, {0, 5}, 0.0f},       {{1, 1}, {-1, -1}, -1.0f},
      {{0, 0}, {0, 0}, 1.0f},       {{0, 0}, {1, 0}, 0.0f},
  };
  for (const Case& c : cases) {
    EXPECT_THAT(CosineSimilarity(c.a, c.b), FloatNear(c.want, 1e-6f));
  }
}

TEST(CodeDistanceTest, ComparesNormalisedCodes) {
  const std::vector<float> a = {3, 0}, b = {0, 0.5f}, c = {6, 0}, zero = {0, 0};
  EXPECT_THAT(CodeDistance(a, b), FloatNear(std::sqrt(2.0f), 1e-6f));
  EXPECT_THAT(CodeDistance(a, c), FloatNear(0.0f, 1e-6f));
  EXPECT_THAT(CodeDistance(a, zero), FloatNear(1.0f, 1e-6f));
  EXPECT_THAT(CodeDistance(zero, zero), FloatNear(0.0f, 1e-6f));
}

TEST(BruteForceIndexTest, ReturnsNearestFirst) {
  BruteForceIndex index(2);
  index.Add(std::vector<float>{1, 0}, 10);
  index.Add(std::vector<float>{0, 1}, 20);
  index.Add(std::vector<float>{1, 1}, 30);
  EXPECT_EQ(index.size(), 3u);
  EXPECT_THAT(index.Search(std::vector<float>{0.1f, 1}, 2),
              ElementsAre(20, 30));
  EXPECT_THAT(index.Search(std::vector<float>{5, 0.2f}, 1), ElementsAre(10));
  // k beyond the size returns everything.
  EXPECT_THAT(index.Search(std::vector<float>{1, 0.9f}, 10),
              ElementsAre(30, 10, 20));
}

TEST(BruteForceIndexTest, TiesKeepInsertionOrder) {
  BruteForceIndex index(2);
  index.Add(std::vector<float>{2, 0}, 1);
  index.Add(std::vector<float>{1, 0}, 2);
  EXPECT_THAT(index.Search(std::vector<float>{1, 0}, 2), ElementsAre(1, 2));
}

TEST(FirstCorrectRankTest, Cases) {
  struct Case {
    std::vector<double> retrieved;
    double query;
    int want;
  };
  const Case cases[] = {
      {{100, 200, 300}, 100, 1},
      {{100, 200, 300}, 290, 3},
      {{100, 200, 300}, 180, 2},
      {{100, 200, 300}, 500, 0},
      {{}, 100, 0},
      {{121, 79, 80}, 100, 3},
  };
  for (const Case& c : cases) {
    std::vector<core::Place> retrieved;
    for (double x : c.retrieved) retrieved.push_back({.x = x});
    EXPECT_EQ(FirstCorrectRank(retrieved, {.x = c.query}, 20.0), c.want)
        << "query " << c.query;
  }
}

TEST(FirstCorrectRankTest, CountsDistanceInThePlane) {
  const std::vector<core::Place> retrieved = {{.x = 0, .y = 3},
                                              {.x = 1, .y = 1}};
  EXPECT_EQ(FirstCorrectRank(retrieved, {.x = 0, .y = 0}, 2.0), 2);
  EXPECT_DOUBLE_EQ(PlaceDistance({.x = 3, .y = 4}, {}), 5.0);
}

}  // namespace
}  // namespace fleetmem::robot
