#include "clients/robot/vo/kitti_clip.h"

#include <string>

#include "gtest/gtest.h"
#include "fleetmem_paths.h"

namespace fleetmem::vo {
namespace {

const std::string kClip1 = std::string(FLEETMEM_DATA_DIR) + "/kitti/clip1";

TEST(ParseKittiCalibration, ReadsIntrinsicsAndBaseline) {
  absl::StatusOr<Camera> c = ParseKittiCalibration(
      "P0: 700 0 600 0 0 701 180 0 0 0 1 0\n"
      "P1: 700 0 600 -350 0 701 180 0 0 0 1 0\n",
      "calib.txt");
  ASSERT_TRUE(c.ok()) << c.status();
  EXPECT_EQ(c->fx, 700);
  EXPECT_EQ(c->fy, 701);
  EXPECT_EQ(c->cx, 600);
  EXPECT_EQ(c->cy, 180);
  EXPECT_DOUBLE_EQ(c->baseline_m, 0.5);
  EXPECT_EQ(ParseKittiCalibration("1 2 3", "c").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseKittiCalibration("", "c").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(ParseKittiCalibration("0 0 600 0 0 701 180 0 0 0 1 x", "c")
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(LoadKittiClip, RealClipWithResize) {
  absl::StatusOr<KittiClip> clip = LoadKittiClip(kClip1, 192, 64);
  ASSERT_TRUE(clip.ok()) << clip.status();
  EXPECT_EQ(clip->left.size(), 51u);
  EXPECT_EQ(clip->right.size(), 51u);
  EXPECT_EQ(clip->left[0].cols, 192);
  EXPECT_EQ(clip->left[0].rows, 64);
  EXPECT_NEAR(clip->camera.baseline_m, 0.537, 1e-3);
  EXPECT_NEAR(clip->camera.fx, 707.0912 * 192 / 1226.0, 1e-6);
  double path = 0.0;
  for (double d : clip->travelled_m) path += d;
  EXPECT_GT(path, 55.0);
  EXPECT_LT(path, 65.0);
  EXPECT_DOUBLE_EQ(clip->ground_truth[10].time_s, 1.0);

  KittiClip sub = SubClip(*clip, 10, 5);
  ASSERT_EQ(sub.left.size(), 5u);
  EXPECT_LT(
      (sub.ground_truth[0].pose.matrix() - Eigen::Matrix4d::Identity()).norm(),
      1e-6);
  EXPECT_EQ(sub.travelled_m[0], 0.0);
  EXPECT_DOUBLE_EQ(sub.travelled_m[1], clip->travelled_m[11]);
  // Relative motions are kept.
  const Eigen::Isometry3d a =
      clip->ground_truth[10].pose.inverse() * clip->ground_truth[14].pose;
  EXPECT_LT((sub.ground_truth[4].pose.matrix() - a.matrix()).norm(), 1e-6);
}

TEST(LoadKittiClip, MissingFolder) {
  EXPECT_EQ(LoadKittiClip("/nonexistent/clip").status().code(),
            absl::StatusCode::kNotFound);
}

}  // namespace
}  // namespace fleetmem::vo
