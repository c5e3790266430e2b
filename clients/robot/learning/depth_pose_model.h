// CL-SLAM's depth and pose networks (Voedisch et al., Sec. 4; learning.md
// "Continual visual odometry"), Monodepth2 style, in libtorch on the CPU and
// sized for a 2-core robot computer. libtorch stays behind this header:
// callers see grey images as cv::Mat and motions as Eigen isometries.
//
//   DepthNet  image (1 x H x W) -> disparity at 4 scales (H/2^s x W/2^s),
//             sigmoid, mapped to depth in [min_depth_m, max_depth_m].
//             Encoder: 5 stride-2 stages (16, 32, 64, 96, 128 channels),
//             decoder with skip connections (Monodepth2's layout).
//   PoseNet   two stacked images (2 x H x W) -> 6 numbers, axis-angle and
//             translation: the pose of the second camera in the first's
//             frame (X_first = T X_second), metric through the velocity term;
//             the rotation outputs are scaled by 0.01 (Monodepth2), the
//             translation is not.
//
// Training on a triplet {I_{t-2}, I_{t-1}, I_t} (Eq. 7):
//   L = L_pr + gamma L_sm + lambda L_vel
//   L_pr   the target I_{t-1} reconstructed from each source by its depth and
//          the predicted motion; per pixel 0.85 (1 - SSIM)/2 + 0.15 |.|
//          (3x3 SSIM), the minimum over the sources, auto-masking (a pixel
//          whose unwarped source already matches better keeps that error
//          and gives no gradient), averaged over the 4 scales at full
//          resolution.
//   L_sm   edge-aware smoothness of the mean-normalised disparity, halved at
//          each coarser scale; gamma = 0.001.
//   L_vel  | ||t|| - travelled distance | of both motions; lambda = 0.05.
// A triplet may carry the right stereo image of its middle frame: it is then
// one more source at the known baseline (pre-training only).
//
// Not thread-safe: one thread drives a model; torch's intra-op threads are
// set with SetTorchThreads (gpl_model.h).
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_DEPTH_POSE_MODEL_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_DEPTH_POSE_MODEL_H_

#include <array>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "Eigen/Geometry"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "opencv2/core.hpp"

namespace fleetmem::vo {

// A pinhole camera in the pixels of its images (principal point at pixel
// centres, KITTI's convention), with the stereo baseline when there is one.
struct Camera {
  double fx = 0.0;
  double fy = 0.0;
  double cx = 0.0;
  double cy = 0.0;
  int width = 0;
  int height = 0;
  double baseline_m = 0.0;
};

struct DepthPoseOptions {
  // Network input: every image is converted to grey and resized to this
  // (KITTI's 1241 x 376 becomes 192 x 64). Multiples of 32.
  int image_width = 192;
  int image_height = 64;
  // Depth range of the disparity mapping (CL-SLAM: 0.1 m; Monodepth2: 100 m
  // as the far end).
  double min_depth_m = 0.1;
  double max_depth_m = 100.0;
  // gamma and lambda of Eq. 7, and SSIM's share of the photometric error.
  float smoothness_weight = 1e-3f;
  float velocity_weight = 0.05f;
  float ssim_weight = 0.85f;
  // Adam's learning rate (CL-SLAM: 1e-4 during adaptation).
  double learning_rate = 1e-4;
  // Seeds torch's generator when the model is created (initial weights).
  uint64_t seed = 1;
};

// One training sample: a triplet of consecutive (accepted) frames, the
// distances travelled from the first to the second and from the second to
// the third (the robot's speed times the frame interval), the camera, and
// optionally the right stereo image of the middle frame.
struct Triplet {
  std::array<cv::Mat, 3> images;
  std::array<double, 2> distances_m = {0.0, 0.0};
  Camera camera;
  cv::Mat right_of_middle;
};

struct VoLosses {
  float total = 0.0f;
  float photometric = 0.0f;
  float smoothness = 0.0f;
  float velocity = 0.0f;
};

class DepthPoseModel {
 public:
  // A model with seeded random weights. INVALID_ARGUMENT for bad options.
  static absl::StatusOr<std::unique_ptr<DepthPoseModel>> Create(
      const DepthPoseOptions& options);
  // Weights and options written by Save. NOT_FOUND, DATA_LOSS (not a depth
  // and pose model file, or weights that do not fit the options) or
  // FAILED_PRECONDITION (another format version).
  static absl::StatusOr<std::unique_ptr<DepthPoseModel>> Load(
      const std::string& path);
  ~DepthPoseModel();
  DepthPoseModel(const DepthPoseModel&) = delete;
  DepthPoseModel& operator=(const DepthPoseModel&) = delete;

  // Options, weights and the frozen flag, through a temporary file renamed
  // into place. INTERNAL on an I/O error (the old file is left as it was).
  absl::Status Save(const std::string& path) const;
  // A deep copy of the weights and the frozen flag, with a fresh optimiser.
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> Clone() const;
  // Replaces this model's weights by `other`'s (same options) and resets the
  // optimiser. INVALID_ARGUMENT if the options differ.
  absl::Status CopyWeightsFrom(const DepthPoseModel& other);

  const DepthPoseOptions& options() const;
  int64_t ParameterCount() const;
  // Freezes both encoders (CL-SLAM's adaptation: only the decoders learn).
  void FreezeEncoders();
  bool encoders_frozen() const;

  // One Adam step of Eq. 7 over the batch. INVALID_ARGUMENT for an empty
  // batch, an empty image or a camera without focal length.
  absl::StatusOr<VoLosses> TrainStep(std::span<const Triplet> batch);
  // The losses of a batch without a step.
  absl::StatusOr<VoLosses> Evaluate(std::span<const Triplet> batch);

  // The pose of `second`'s camera in `first`'s frame.
  absl::StatusOr<Eigen::Isometry3d> PredictMotion(const cv::Mat& first,
                                                  const cv::Mat& second);
  // Depth in metres at the network's input size (CV_32F).
  absl::StatusOr<cv::Mat> PredictDepth(const cv::Mat& image);
  // The depth encoder's bottleneck, flattened (the replay buffer's
  // similarity feature; stable while the encoders are frozen).
  absl::StatusOr<std::vector<float>> Feature(const cv::Mat& image);

 private:
  struct Impl;
  explicit DepthPoseModel(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// The pieces of the loss on hand-made inputs (tests): the same functions the
// training step runs, on images in [0, 255] (CV_8U or CV_32F, one channel).
//
// `source` sampled at the projections of `target_depth`'s pixels (metres,
// CV_32F, the camera's size) through `source_in_target`, the source camera's
// pose in the target's frame. Pixels projecting outside take the border.
absl::StatusOr<cv::Mat> WarpToTarget(const cv::Mat& source,
                                     const cv::Mat& target_depth,
                                     const Eigen::Isometry3d& source_in_target,
                                     const Camera& camera);
// L_pr of one scale: the per-pixel minimum over the warped sources (and, with
// `automask`, the unwarped ones) of the photometric error, averaged.
absl::StatusOr<float> ReprojectionLoss(
    const cv::Mat& target, std::span<const cv::Mat> sources,
    const cv::Mat& target_depth,
    std::span<const Eigen::Isometry3d> sources_in_target, const Camera& camera,
    bool automask, float ssim_weight = 0.85f);
// The isometry of PoseNet's 6 outputs (axis-angle, translation).
Eigen::Isometry3d PoseFromParameters(const std::array<float, 6>& parameters);

// `camera` for an image resized to width x height.
Camera ResizedCamera(const Camera& camera, int width, int height);

}  // namespace fleetmem::vo

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_DEPTH_POSE_MODEL_H_
