// CL-SLAM's continual visual odometry (Voedisch et al. Secs. 4-5;
// learning.md "Continual visual odometry") on the robot: pre-training, then
// deployments in sequence, each adapting online.
//
// Per deployment, for each new frame that is at least `min_motion_m` from
// the last accepted one (closer frames are skipped for adaptation, their pose
// is predicted from the last accepted frame):
//   (1) the triplet of the last three accepted frames and their travelled
//       distances;
//   (2)-(5) `update_steps` (c = 5) Adam steps of Eq. 7 on the triplet (the
//       expert) and on the triplet plus one replayed triplet of every other
//       environment (the generalizer), encoders frozen;
//   then the odometry network's motion from the previous accepted frame is
//   chained onto its pose. The triplet is offered to the replay buffer of
//   the current environment (replay_buffer.h).
// At the end the stored weights that initialise the next deployment are
// replaced (CL-SLAM: by the generalizer's; the expert is discarded).
//
// Methods (CL-SLAM's baselines):
//   fixed             the stored weights, no adaptation (B_fixed);
//   expert_only       one network adapted on the online stream, carried over
//                     to the next deployment (B_expert, Li et al.);
//   generalizer_only  one network adapted on online + replayed data, carried
//                     over (B_general, CoMoDA);
//   cl_slam           both: the expert gives the odometry, the generalizer
//                     initialises the next deployment.
//
// Loop closure (CL-SLAM's public code): a frame whose frozen-encoder feature
// has cosine similarity >= loop_similarity with a frame at least
// loop_min_gap_frames earlier gives a loop; PoseNet estimates its relative
// pose and the pose graph (clients/robot/slam) of odometry and loop edges is
// optimised.
#ifndef FLEETMEM_CLIENTS_ROBOT_VO_CONTINUAL_VO_H_
#define FLEETMEM_CLIENTS_ROBOT_VO_CONTINUAL_VO_H_

#include <functional>
#include <memory>
#include <random>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "clients/robot/learning/depth_pose_model.h"
#include "clients/robot/slam/pose_graph.h"
#include "clients/robot/slam/trajectory.h"
#include "clients/robot/vo/kitti_clip.h"
#include "clients/robot/vo/replay_buffer.h"

namespace fleetmem::vo {

enum class VoMethod { kFixed, kExpertOnly, kGeneralizerOnly, kClSlam };
// "fixed", "expert_only", "generalizer_only", "cl_slam".
absl::StatusOr<VoMethod> ParseVoMethod(std::string_view name);
std::string VoMethodName(VoMethod method);

struct ContinualVoOptions {
  // c: update steps per new frame (CL-SLAM Table 5: 5).
  int update_steps = 5;
  // Frames that moved less than this since the last accepted one are not
  // used for adaptation (CL-SLAM: 0.2 m).
  double min_motion_m = 0.2;
  ReplayOptions replay;
  // Loop candidates: feature cosine similarity and minimum frame gap (the
  // public code's 0.99 and 250).
  double loop_similarity = 0.99;
  int loop_min_gap_frames = 250;
  // Seeds the replay draws.
  uint64_t seed = 1;
};

struct DeploymentResult {
  // The odometry network's trajectory, one pose per frame, stamped like the
  // clip's ground truth; `optimized` after the pose graph (equal to
  // `odometry` when no loop closed).
  slam::Trajectory odometry;
  slam::Trajectory optimized;
  // cl_slam only: the generalizer's own chained estimates (diagnostic).
  slam::Trajectory generalizer_odometry;
  int adapted_frames = 0;
  int skipped_frames = 0;
  int update_steps = 0;
  int loops = 0;
  double seconds = 0.0;
  VoLosses last_losses;
};

// Pre-training (the paper's Cityscapes stage, here on a clip): `steps` Adam
// steps on batches of random triplets of consecutive frames, with the right
// stereo image as an extra source when the clip has one and `stereo` is
// set. The encoders are frozen afterwards.
struct PretrainOptions {
  int steps = 600;
  int batch_size = 4;
  bool stereo = true;
  uint64_t seed = 1;
};
absl::StatusOr<VoLosses> Pretrain(
    DepthPoseModel& model, const KittiClip& clip,
    const PretrainOptions& options,
    const std::function<void(int step, const VoLosses&)>& progress = {});

// The triplet of frames a < b < c of a clip (no right image).
Triplet ClipTriplet(const KittiClip& clip, size_t a, size_t b, size_t c);

class ContinualVo {
 public:
  // Starts from a copy of `initial` (whose encoders are frozen here).
  static absl::StatusOr<std::unique_ptr<ContinualVo>> Create(
      const DepthPoseModel& initial, VoMethod method,
      const ContinualVoOptions& options = {});
  // A copy of the whole state (weights, replay memory, random draws), to
  // branch a deployment sequence.
  absl::StatusOr<std::unique_ptr<ContinualVo>> Clone() const;

  // Offers every triplet of a clip seen before deployment (pre-training) to
  // the replay buffer of `environment`.
  absl::Status Remember(const std::string& environment, const KittiClip& clip);
  // One deployment in `environment`; `progress` sees each frame.
  absl::StatusOr<DeploymentResult> Deploy(
      const std::string& environment, const KittiClip& clip,
      const std::function<void(size_t frame, size_t frames)>& progress = {});

  VoMethod method() const { return method_; }
  // The weights that initialise the next deployment.
  const DepthPoseModel& weights() const { return *weights_; }
  const ReplayMemory& replay() const { return replay_; }

 private:
  ContinualVo(std::unique_ptr<DepthPoseModel> weights, VoMethod method,
              const ContinualVoOptions& options);
  // Deploy's steps: update_steps training steps on the `online` triplet
  // (the expert on it alone, the generalizer with replayed triplets of
  // other environments; either may be null), counted in `result`; the loop
  // edges from frame i to frames at least loop_min_gap_frames back whose
  // features are alike (how many the graph took).
  // The deployment's models, copies of weights_: the expert (every method
  // but generalizer_only) and the generalizer (cl_slam, generalizer_only).
  absl::Status CloneModels(std::unique_ptr<DepthPoseModel>& expert,
                           std::unique_ptr<DepthPoseModel>& generalizer) const;
  absl::Status Adapt(const std::string& environment, const Triplet& online,
                     DepthPoseModel* expert, DepthPoseModel* generalizer,
                     DeploymentResult& result);
  absl::StatusOr<size_t> AddLoops(
      const KittiClip& clip, const std::vector<std::vector<float>>& features,
      size_t i, DepthPoseModel& odometer, slam::PoseGraph3d& graph) const;

  std::unique_ptr<DepthPoseModel> weights_;
  VoMethod method_;
  ContinualVoOptions options_;
  ReplayMemory replay_;
  std::mt19937_64 rng_;
};

}  // namespace fleetmem::vo

#endif  // FLEETMEM_CLIENTS_ROBOT_VO_CONTINUAL_VO_H_
