#include "clients/robot/vo/classical_vo.h"

#include <string>

#include "clients/robot/slam/trajectory_metrics.h"
#include "gtest/gtest.h"
#include "fleetmem_paths.h"

namespace fleetmem::vo {
namespace {

// The baseline on the real clips: the essential matrix with the known speed
// follows both the straight clip and the turn within a few metres.
TEST(ClassicalVo, FollowsTheRealClips) {
  for (const char* name : {"clip1", "clip2"}) {
    absl::StatusOr<KittiClip> clip =
        LoadKittiClip(std::string(FLEETMEM_DATA_DIR) + "/kitti/" + name);
    ASSERT_TRUE(clip.ok()) << clip.status();
    absl::StatusOr<ClassicalVoResult> vo = RunClassicalVo(*clip);
    ASSERT_TRUE(vo.ok()) << vo.status();
    ASSERT_EQ(vo->odometry.size(), clip->left.size());
    absl::StatusOr<slam::AteResult> ate = slam::AbsoluteTrajectoryError(
        clip->ground_truth, vo->odometry, slam::Alignment::kSe3);
    ASSERT_TRUE(ate.ok());
    EXPECT_LT(ate->translation_m.rmse, 3.0) << name;
    // The heading change over the clip (clip 2 turns by about 98 degrees).
    const double truth =
        Eigen::AngleAxisd(clip->ground_truth.back().pose.linear()).angle();
    const double estimate =
        Eigen::AngleAxisd(vo->odometry.back().pose.linear()).angle();
    EXPECT_NEAR(estimate, truth, 10.0 * M_PI / 180.0) << name;
  }
}

TEST(ClassicalVo, RejectsAnEmptyClip) {
  EXPECT_EQ(RunClassicalVo(KittiClip{}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fleetmem::vo
