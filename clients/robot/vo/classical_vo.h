// The classical baseline of the continual-VO evaluation: monocular feature
// tracking with the essential matrix, scaled by the known speed (the same
// travelled distances that supervise the networks' scale). Shi-Tomasi
// corners tracked by pyramidal Lucas-Kanade, RANSAC on the five-point
// essential matrix, the cheirality check of recoverPose; the unit
// translation is multiplied by the distance travelled since the previous
// frame. Frames that give too few inliers keep a constant-velocity motion.
// Nothing is learned, so it neither adapts nor forgets.
#ifndef FLEETMEM_CLIENTS_ROBOT_VO_CLASSICAL_VO_H_
#define FLEETMEM_CLIENTS_ROBOT_VO_CLASSICAL_VO_H_

#include "absl/status/statusor.h"
#include "clients/robot/slam/trajectory.h"
#include "clients/robot/vo/kitti_clip.h"

namespace fleetmem::vo {

struct ClassicalVoOptions {
  int max_corners = 1500;
  double corner_quality = 0.01;
  double min_corner_distance_px = 7.0;
  // RANSAC threshold on the epipolar error, in pixels of the full image.
  double ransac_threshold_px = 1.0;
  // Fewer inliers than this: the frame keeps the previous motion.
  int min_inliers = 30;
};

struct ClassicalVoResult {
  slam::Trajectory odometry;
  int fallback_frames = 0;
};

// INVALID_ARGUMENT for a clip without frames.
absl::StatusOr<ClassicalVoResult> RunClassicalVo(
    const KittiClip& clip, const ClassicalVoOptions& options = {});

}  // namespace fleetmem::vo

#endif  // FLEETMEM_CLIENTS_ROBOT_VO_CLASSICAL_VO_H_
