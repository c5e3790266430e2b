#include "services/core/place_metrics.h"

#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

TEST(PlaceMetricsTest, HandComputedExample) {
  // Ten queries: first correct ranks 1,1,1,2,3,6,7,0,0,1.
  const FirstCorrectRanks ranks = {1, 1, 1, 2, 3, 6, 7, 0, 0, 1};
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 1), 0.4);
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 2), 0.5);
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 3), 0.6);
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 5), 0.6);
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 6), 0.7);
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 7), 0.8);
  EXPECT_DOUBLE_EQ(RecallAtK(ranks, 100), 0.8);
  // WR = 0.5*0.4 + 0.1*(0.5 + 0.6 + 0.6 + 0.6 + 0.7) = 0.2 + 0.3 = 0.5.
  EXPECT_NEAR(WeightedRecall(ranks), 0.5, 1e-12);
}

TEST(PlaceMetricsTest, PerfectAndEmpty) {
  EXPECT_NEAR(WeightedRecall({1, 1, 1}), 1.0, 1e-12);
  EXPECT_EQ(RecallAtK({}, 1), 0.0);
  EXPECT_EQ(WeightedRecall({}), 0.0);
  EXPECT_EQ(WeightedRecall({0, 0}), 0.0);
}

}  // namespace
}  // namespace fleetmem::core
