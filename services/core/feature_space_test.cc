#include "services/core/feature_space.h"

#include <cmath>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

TEST(NormalizedCodeTest, ScalesToUnitNorm) {
  const std::vector<float> code = {3.0f, 4.0f};
  const std::vector<float> normalized = NormalizedCode(code);
  ASSERT_EQ(normalized.size(), 2u);
  EXPECT_FLOAT_EQ(normalized[0], 0.6f);
  EXPECT_FLOAT_EQ(normalized[1], 0.8f);
}

TEST(NormalizedCodeTest, ZeroCodeStaysZero) {
  const std::vector<float> code = {0.0f, 0.0f, 0.0f};
  EXPECT_EQ(NormalizedCode(code), code);
}

TEST(FeatureSpatialCodeTest, AppendsScaledPlace) {
  MemoryTrace trace;
  trace.code = {0.0f, 2.0f};
  trace.place = {.x = 10.0, .y = -20.0, .z = 5.0, .yaw = 1.0};
  const Eigen::VectorXf c = FeatureSpatialCode(trace, 10.0);
  ASSERT_EQ(c.size(), 5);
  EXPECT_FLOAT_EQ(c[0], 0.0f);
  EXPECT_FLOAT_EQ(c[1], 1.0f);
  EXPECT_FLOAT_EQ(c[2], 1.0f);
  EXPECT_FLOAT_EQ(c[3], -2.0f);
  EXPECT_FLOAT_EQ(c[4], 0.5f);
}

TEST(CodeDistanceTest, ComparesNormalisedCodes) {
  const std::vector<float> a = {1.0f, 0.0f};
  const std::vector<float> a_scaled = {7.0f, 0.0f};
  const std::vector<float> b = {0.0f, 3.0f};
  const std::vector<float> minus_a = {-2.0f, 0.0f};
  EXPECT_FLOAT_EQ(CodeDistance(a, a_scaled), 0.0f);
  EXPECT_FLOAT_EQ(CodeDistance(a, b), std::sqrt(2.0f));
  EXPECT_FLOAT_EQ(CodeDistance(a, minus_a), 2.0f);
  EXPECT_FLOAT_EQ(CodeDistance(b, a), CodeDistance(a, b));
}

}  // namespace
}  // namespace fleetmem::core
