#include "clients/robot/slam/scan_matcher.h"

#include <cmath>

#include "gtest/gtest.h"

namespace fleetmem::slam {
namespace {

// A scan of 180 beams over 180 degrees taken at `pose` in a room with
// walls at x = 0 and x = 8, y = 0 and y = 5, plus a pillar's corner at
// (5, 2)-(5.5, 2.6).
robot::LaserScan RoomScan(const Pose2& pose, bool other_room = false) {
  struct Seg {
    Eigen::Vector2d a, b;
  };
  std::vector<Seg> walls = {{{0, 0}, {8, 0}},       {{8, 0}, {8, 5}},
                            {{8, 5}, {0, 5}},       {{0, 5}, {0, 0}},
                            {{5, 2}, {5.5, 2}},     {{5.5, 2}, {5.5, 2.6}},
                            {{5.5, 2.6}, {5, 2.6}}, {{5, 2.6}, {5, 2}}};
  if (other_room)
    walls = {{{-3, -1}, {12, -1}},
             {{12, -1}, {12, 9}},
             {{12, 9}, {-3, 9}},
             {{-3, 9}, {-3, -1}}};
  robot::LaserScan scan;
  scan.max_range = 50;
  for (int i = 0; i < 180; ++i) {
    const double bearing = pose.yaw - M_PI / 2 + M_PI * i / 179;
    const Eigen::Vector2d o(pose.x, pose.y),
        d(std::cos(bearing), std::sin(bearing));
    double best = 0.0;
    for (const Seg& w : walls) {
      const Eigen::Vector2d e = w.b - w.a;
      Eigen::Matrix2d m;
      m << d, -e;
      if (std::abs(m.determinant()) < 1e-12) continue;
      const Eigen::Vector2d st = m.inverse() * (w.a - o);
      if (st(0) > 0 && st(1) >= 0 && st(1) <= 1 && (best == 0 || st(0) < best))
        best = st(0);
    }
    scan.ranges.push_back(static_cast<float>(best));
  }
  return scan;
}

TEST(ScanMatcherTest, RecoversTheRelativePose) {
  const Pose2 a{2.0, 2.5, 0.1}, b{2.6, 2.2, 0.35};
  const ScanMatcher matcher(ScanPoints(RoomScan(a), 30));
  const ScanMatch m = matcher.Match(ScanPoints(RoomScan(b), 30), Pose2{});
  const Pose2 truth = Between(a, b);
  ASSERT_TRUE(m.accepted) << m.inlier_ratio << " " << m.rms_m;
  EXPECT_NEAR(m.pose.x, truth.x, 0.02);
  EXPECT_NEAR(m.pose.y, truth.y, 0.02);
  EXPECT_NEAR(m.pose.yaw, truth.yaw, 0.01);
}

TEST(ScanMatcherTest, FindsAFarTurnFromSeveralGuesses) {
  const Pose2 a{2.0, 2.5, 0.0}, b{2.3, 2.4, 0.9};
  const ScanMatcher matcher(ScanPoints(RoomScan(a), 30));
  const ScanMatch m = matcher.MatchBest(
      ScanPoints(RoomScan(b), 30), InitialGuesses({}, M_PI, M_PI / 12, 0, 0));
  ASSERT_TRUE(m.accepted);
  EXPECT_NEAR(m.pose.yaw, Between(a, b).yaw, 0.01);
}

TEST(ScanMatcherTest, RejectsADifferentPlace) {
  const ScanMatcher matcher(ScanPoints(RoomScan({2, 2.5, 0}), 30));
  const ScanMatch m = matcher.MatchBest(
      ScanPoints(RoomScan({2, 2.5, 0}, /*other_room=*/true), 30),
      InitialGuesses({}, M_PI, M_PI / 6, 0, 0));
  EXPECT_FALSE(m.accepted);
}

TEST(ScanCodecTest, RoundTripsToTheMillimetre) {
  robot::LaserScan scan = RoomScan({2, 2.5, 0.3});
  scan.ranges[3] = 0.0f;
  absl::StatusOr<robot::LaserScan> back = DecodeScan(EncodeScan(scan));
  ASSERT_TRUE(back.ok()) << back.status();
  ASSERT_EQ(back->ranges.size(), scan.ranges.size());
  for (size_t i = 0; i < scan.ranges.size(); ++i) {
    EXPECT_NEAR(back->ranges[i], scan.ranges[i], 0.0006);
  }
  EXPECT_FALSE(DecodeScan("abc").ok());
  EXPECT_FALSE(DecodeScan(EncodeScan(scan).substr(0, 20)).ok());
}

}  // namespace
}  // namespace fleetmem::slam
