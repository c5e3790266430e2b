// A KITTI odometry clip as the robot's camera sees it: the left (and right)
// grey frames, the calibration, the ground-truth poses and the distance
// travelled between frames (the robot's speed times the frame interval; the
// clips carry no speedometer, so it comes from the poses, as CL-SLAM takes
// it from the vehicle's odometry).
//
// Layout (../shared/data/kitti/clip1): image_l/NNNNNN.png, image_r/...,
// calib.txt (P0 and P1, 12 numbers each, optionally prefixed "P0:"),
// poses.txt (KITTI: 3x4 row-major, frame 0 = identity). Frames are 10 Hz.
#ifndef FLEETMEM_CLIENTS_ROBOT_VO_KITTI_CLIP_H_
#define FLEETMEM_CLIENTS_ROBOT_VO_KITTI_CLIP_H_

#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/learning/depth_pose_model.h"
#include "clients/robot/slam/trajectory.h"
#include "opencv2/core.hpp"

namespace fleetmem::vo {

struct KittiClip {
  std::string name;
  Camera camera;  // of the images as stored (after any resize: see below)
  std::vector<cv::Mat> left;   // 8-bit grey
  std::vector<cv::Mat> right;  // empty when the clip has no image_r/
  // Ground truth, stamped i * frame_interval_s.
  slam::Trajectory ground_truth;
  // travelled_m[i]: distance from frame i-1 to i (0 for frame 0).
  std::vector<double> travelled_m;
  double frame_interval_s = 0.1;
};

// Camera from calib.txt's text: fx, fy, cx, cy of P0 and the baseline
// -P1[0][3] / P1[0][0] (0 without P1). INVALID_ARGUMENT naming `name`.
absl::StatusOr<Camera> ParseKittiCalibration(std::string_view text,
                                             const std::string& name);

// Loads a clip; with width/height > 0 every image is resized to that (and
// the camera with it), which keeps a replay buffer small. NOT_FOUND for a
// missing folder or file, INVALID_ARGUMENT for unreadable content or a
// count of poses that differs from the count of left frames.
absl::StatusOr<KittiClip> LoadKittiClip(const std::string& dir, int width = 0,
                                        int height = 0);

// Frames [first, first + count) of a clip (a shorter clip for quick runs).
KittiClip SubClip(const KittiClip& clip, size_t first, size_t count);

}  // namespace fleetmem::vo

#endif  // FLEETMEM_CLIENTS_ROBOT_VO_KITTI_CLIP_H_
