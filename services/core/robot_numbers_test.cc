#include "services/core/robot_numbers.h"

#include <string>

#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

TEST(RobotNumbersTest, NumbersInOrderOfFirstSightAndPacksBothWays) {
  RobotNumbers robots;
  EXPECT_FALSE(robots.Find("a", 1).has_value());
  const PackedTraceKey a1 = robots.Pack("a", 1);
  const PackedTraceKey b7 = robots.Pack("b", 7);
  const std::string long_id(100, 'z');  // beyond the short-string buffer
  const PackedTraceKey z3 = robots.Pack(long_id, 3);
  EXPECT_EQ(a1.robot, 0u);
  EXPECT_EQ(b7.robot, 1u);
  EXPECT_EQ(z3.robot, 2u);
  EXPECT_EQ(robots.Pack("a", 9).robot, 0u);  // known: the same number
  EXPECT_EQ(robots.size(), 3u);
  EXPECT_EQ(robots.Find("b", 7), b7);
  EXPECT_EQ(robots.Unpack(z3), (TraceKey{long_id, 3}));
  EXPECT_EQ(robots.robot_id(1), "b");
  EXPECT_FALSE(robots.Add("b"));
  EXPECT_TRUE(robots.Add("c"));
  EXPECT_EQ(robots.Find("c", 0)->robot, 3u);
  EXPECT_NE(robots.Find("a", 1), robots.Find("a", 2));
  robots.Clear();
  EXPECT_EQ(robots.size(), 0u);
  EXPECT_FALSE(robots.Find("a", 1).has_value());
}

}  // namespace
}  // namespace fleetmem::core
