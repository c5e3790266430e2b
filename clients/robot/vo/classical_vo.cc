#include "clients/robot/vo/classical_vo.h"

#include <vector>

#include "opencv2/calib3d.hpp"
#include "opencv2/imgproc.hpp"
#include "opencv2/video/tracking.hpp"

namespace fleetmem::vo {

absl::StatusOr<ClassicalVoResult> RunClassicalVo(
    const KittiClip& clip, const ClassicalVoOptions& options) {
  if (clip.left.empty()) {
    return absl::InvalidArgumentError("the clip has no frames");
  }
  const cv::Mat k =
      (cv::Mat_<double>(3, 3) << clip.camera.fx, 0.0, clip.camera.cx, 0.0,
       clip.camera.fy, clip.camera.cy, 0.0, 0.0, 1.0);
  ClassicalVoResult result;
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  Eigen::Isometry3d last_motion = Eigen::Isometry3d::Identity();
  result.odometry.push_back({0.0, pose});
  for (size_t i = 1; i < clip.left.size(); ++i) {
    std::vector<cv::Point2f> previous, current;
    cv::goodFeaturesToTrack(clip.left[i - 1], previous, options.max_corners,
                            options.corner_quality,
                            options.min_corner_distance_px);
    Eigen::Isometry3d motion = last_motion;
    bool estimated = false;
    if (previous.size() >= 8) {
      std::vector<unsigned char> status;
      std::vector<float> error;
      cv::calcOpticalFlowPyrLK(clip.left[i - 1], clip.left[i], previous,
                               current, status, error);
      std::vector<cv::Point2f> a, b;
      for (size_t j = 0; j < status.size(); ++j) {
        if (status[j]) {
          a.push_back(previous[j]);
          b.push_back(current[j]);
        }
      }
      if (static_cast<int>(a.size()) >= options.min_inliers) {
        cv::Mat inliers;
        cv::Mat e = cv::findEssentialMat(a, b, k, cv::RANSAC, 0.999,
                                         options.ransac_threshold_px, inliers);
        cv::Mat r, t;
        if (e.rows == 3 && e.cols == 3) {
          const int good = cv::recoverPose(e, a, b, k, r, t, inliers);
          if (good >= options.min_inliers) {
            // recoverPose: x_i = R x_{i-1} + t; the camera i in frame i-1
            // is the inverse.
            Eigen::Isometry3d step = Eigen::Isometry3d::Identity();
            Eigen::Matrix3d rot;
            for (int row = 0; row < 3; ++row) {
              for (int col = 0; col < 3; ++col) {
                rot(row, col) = r.at<double>(row, col);
              }
            }
            step.linear() = rot;
            step.translation() = Eigen::Vector3d(
                t.at<double>(0), t.at<double>(1), t.at<double>(2));
            motion = step.inverse();
            motion.translation() =
                motion.translation().normalized() * clip.travelled_m[i];
            estimated = true;
          }
        }
      }
    }
    if (!estimated) {
      ++result.fallback_frames;
      const double norm = motion.translation().norm();
      if (norm > 0.0) {
        motion.translation() *= clip.travelled_m[i] / norm;
      }
    }
    last_motion = motion;
    pose = pose * motion;
    result.odometry.push_back({i * clip.frame_interval_s, pose});
  }
  return result;
}

}  // namespace fleetmem::vo
