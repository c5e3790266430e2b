#include "clients/robot/slam/pose_graph.h"

#include <cmath>
#include <random>

#include "gtest/gtest.h"

namespace fleetmem::slam {
namespace {

// A robot driving a 10 m square twice, 1 m per step: true poses, and
// odometry with noise (seeded).
struct Drive {
  std::vector<Pose2> truth;
  std::vector<Pose2> odometry;  // relative motions, noisy
};

Drive SquareDrive(uint32_t seed) {
  Drive d;
  std::mt19937 rng(seed);
  std::normal_distribution<double> dxy(0.0, 0.03), dyaw(0.0, 0.005);
  Pose2 p;
  for (int lap = 0; lap < 2; ++lap) {
    for (int side = 0; side < 4; ++side) {
      for (int i = 0; i < 10; ++i) {
        d.truth.push_back(p);
        const Pose2 step{1.0, 0.0, i == 9 ? M_PI / 2 : 0.0};
        p = Compose(p, step);
        d.odometry.push_back(
            Pose2{step.x + dxy(rng), step.y + dxy(rng), step.yaw + dyaw(rng)});
      }
    }
  }
  d.odometry.pop_back();
  return d;
}

// The graph of a drive: odometry chain plus true loops between the laps.
PoseGraph2d BuildGraph(const Drive& d, const PoseGraphOptions& options) {
  PoseGraph2d g(options);
  Pose2 p = d.truth[0];
  g.AddNode(p);
  const Eigen::Matrix3d odo_info =
      Eigen::Vector3d(1 / 0.0009, 1 / 0.0009, 1 / 0.000025).asDiagonal();
  for (size_t i = 0; i < d.odometry.size(); ++i) {
    p = Compose(p, d.odometry[i]);
    g.AddNode(p);
    EXPECT_TRUE(
        g.AddEdge(i, i + 1, d.odometry[i], odo_info, EdgeKind::kOdometry).ok());
  }
  const Eigen::Matrix3d loop_info =
      Eigen::Vector3d(400, 400, 2500).asDiagonal();
  for (size_t i = 0; i + 40 < d.truth.size(); i += 5) {
    EXPECT_TRUE(g.AddEdge(i, i + 40, Between(d.truth[i], d.truth[i + 40]),
                          loop_info, EdgeKind::kLoop)
                    .ok());
  }
  return g;
}

double MaxDifference(const PoseGraph2d& a, const PoseGraph2d& b) {
  double worst = 0.0;
  for (size_t i = 0; i < a.num_nodes(); ++i) {
    worst = std::max(worst, std::hypot(a.pose(i).x - b.pose(i).x,
                                       a.pose(i).y - b.pose(i).y));
  }
  return worst;
}

// How far the second lap is from the first (the loops say: not at all).
double LapDisagreement(const PoseGraph2d& g) {
  double worst = 0.0;
  for (size_t i = 0; i + 40 < g.num_nodes(); ++i) {
    worst = std::max(worst, std::hypot(g.pose(i + 40).x - g.pose(i).x,
                                       g.pose(i + 40).y - g.pose(i).y));
  }
  return worst;
}

TEST(PoseGraph2dTest, LoopsRemoveTheOdometryDrift) {
  const Drive d = SquareDrive(7);
  PoseGraph2d g = BuildGraph(d, {});
  const double before = LapDisagreement(g);
  absl::StatusOr<SolveReport> r = g.Optimize();
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_TRUE(r->rejected_loops.empty()) << r->rejected_loops.size();
  EXPECT_GT(before, 0.3);
  EXPECT_LT(LapDisagreement(g), before / 3) << before;
}

TEST(PoseGraph2dTest, AddingALoopReoptimisesFromTheLastSolution) {
  const Drive d = SquareDrive(8);
  PoseGraph2d g = BuildGraph(d, {});
  ASSERT_TRUE(g.Optimize().ok());
  const Pose2 loop = Between(d.truth[3], d.truth[43]);
  const Eigen::Matrix3d info = Eigen::Matrix3d::Identity() * 400;
  ASSERT_TRUE(g.AddEdge(3, 43, loop, info, EdgeKind::kLoop).ok());
  absl::StatusOr<SolveReport> warm = g.Optimize();
  ASSERT_TRUE(warm.ok());
  PoseGraph2d cold = BuildGraph(d, {});
  ASSERT_TRUE(cold.AddEdge(3, 43, loop, info, EdgeKind::kLoop).ok());
  absl::StatusOr<SolveReport> from_odometry = cold.Optimize();
  ASSERT_TRUE(from_odometry.ok());
  // Warm start: already near the optimum, so fewer iterations and the same
  // answer.
  EXPECT_LE(warm->iterations, from_odometry->iterations);
  EXPECT_LT(warm->initial_cost, from_odometry->initial_cost / 10);
  EXPECT_LT(MaxDifference(g, cold), 1e-3);
}

// The acceptance check: a deliberately wrong loop (8 m and 90 degrees off)
// does not move the optimised trajectory by more than its robust loss
// allows, and is switched off; the same edge without the robust loss
// (quadratic) wrecks the map, so the test can fail.
TEST(PoseGraph2dTest, AWrongLoopDoesNotWreckTheMap) {
  const Drive d = SquareDrive(9);
  PoseGraph2d clean = BuildGraph(d, {});
  ASSERT_TRUE(clean.Optimize().ok());
  const Pose2 wrong =
      Compose(Between(d.truth[12], d.truth[55]), Pose2{8.0, 0.0, M_PI / 2});
  const Eigen::Matrix3d info = Eigen::Vector3d(400, 400, 2500).asDiagonal();

  PoseGraph2d robust = BuildGraph(d, {});
  ASSERT_TRUE(robust.AddEdge(12, 55, wrong, info, EdgeKind::kLoop).ok());
  absl::StatusOr<SolveReport> r = robust.Optimize();
  ASSERT_TRUE(r.ok());
  ASSERT_EQ(r->rejected_loops.size(), 1u);
  EXPECT_EQ(robust.edges()[r->rejected_loops[0]].to, 55u);
  EXPECT_LT(MaxDifference(robust, clean), 0.01);

  // Robust loss only (no rejection): bounded by the loss, not removed.
  PoseGraph2d bounded = BuildGraph(d, {.outlier_sigma = 0});
  ASSERT_TRUE(bounded.AddEdge(12, 55, wrong, info, EdgeKind::kLoop).ok());
  ASSERT_TRUE(bounded.Optimize().ok());
  EXPECT_LT(MaxDifference(bounded, clean), 0.2);

  PoseGraph2d quadratic =
      BuildGraph(d, {.loop_loss_scale = 1e9, .outlier_sigma = 0});
  ASSERT_TRUE(quadratic.AddEdge(12, 55, wrong, info, EdgeKind::kLoop).ok());
  ASSERT_TRUE(quadratic.Optimize().ok());
  EXPECT_GT(MaxDifference(quadratic, clean), 1.0);
}

TEST(PoseGraph2dTest, RefusesBadEdgesAndLeavesTheGraphAlone) {
  PoseGraph2d g;
  g.AddNode({});
  g.AddNode({1, 0, 0});
  EXPECT_FALSE(
      g.AddEdge(0, 2, {}, Eigen::Matrix3d::Identity(), EdgeKind::kOdometry)
          .ok());
  EXPECT_FALSE(
      g.AddEdge(1, 1, {}, Eigen::Matrix3d::Identity(), EdgeKind::kOdometry)
          .ok());
  Eigen::Matrix3d bad = Eigen::Matrix3d::Identity();
  bad(0, 0) = -1;
  EXPECT_FALSE(g.AddEdge(0, 1, {}, bad, EdgeKind::kOdometry).ok());
  EXPECT_TRUE(g.edges().empty());
  EXPECT_FALSE(PoseGraph2d().Optimize().ok());
}

// SE(3): a helix with drifting odometry and loops between turns.
TEST(PoseGraph3dTest, LoopsRemoveTheOdometryDrift) {
  std::mt19937 rng(5);
  std::normal_distribution<double> n(0.0, 0.005);
  std::vector<Eigen::Isometry3d> truth;
  for (int i = 0; i < 60; ++i) {
    const double a = i * 2 * M_PI / 20;
    Eigen::Isometry3d p = Eigen::Isometry3d::Identity();
    p.translation() << 5 * std::cos(a), 5 * std::sin(a), 0.05 * i;
    p.linear() = Eigen::AngleAxisd(a + M_PI / 2, Eigen::Vector3d::UnitZ())
                     .toRotationMatrix();
    truth.push_back(p);
  }
  PoseGraph3d g;
  Eigen::Isometry3d p = truth[0];
  g.AddNode(p);
  using Info = PoseGraph3d::Information;
  for (size_t i = 0; i + 1 < truth.size(); ++i) {
    Eigen::Isometry3d noise = Eigen::Isometry3d::Identity();
    noise.translation() << n(rng), n(rng), n(rng);
    noise.linear() = (Eigen::AngleAxisd(n(rng), Eigen::Vector3d::UnitX()) *
                      Eigen::AngleAxisd(n(rng), Eigen::Vector3d::UnitY()) *
                      Eigen::AngleAxisd(n(rng), Eigen::Vector3d::UnitZ()))
                         .toRotationMatrix();
    const Eigen::Isometry3d z = truth[i].inverse() * truth[i + 1] * noise;
    p = p * z;
    g.AddNode(p);
    ASSERT_TRUE(
        g.AddEdge(i, i + 1, z, Info::Identity() * 2500, EdgeKind::kOdometry)
            .ok());
  }
  for (size_t i = 0; i + 20 < truth.size(); i += 4) {
    ASSERT_TRUE(g.AddEdge(i, i + 20, truth[i].inverse() * truth[i + 20],
                          Info::Identity() * 2500, EdgeKind::kLoop)
                    .ok());
  }
  auto worst = [&] {
    double w = 0;
    for (size_t i = 0; i < truth.size(); ++i) {
      w = std::max(w,
                   (g.pose(i).translation() - truth[i].translation()).norm());
    }
    return w;
  };
  const double before = worst();
  ASSERT_TRUE(g.Optimize().ok());
  EXPECT_GT(before, 0.3);
  EXPECT_LT(worst(), before / 3);
}

}  // namespace
}  // namespace fleetmem::slam
