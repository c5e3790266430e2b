// One deployment of the continual visual odometry on a robot
// (fleetmem-robot --vo): the robot's stored weights (DATA_DIR/vo-weights.pt,
// or the fleet's pre-trained file for the first deployment), one pass over a
// KITTI-layout image sequence adapting online as CL-SLAM does, then the
// weights for the next deployment written back (through a temporary file
// renamed into place) and the trajectory written in KITTI and TUM format:
//   DATA_DIR/vo/<environment>-<n>/trajectory.{kitti,tum}  after the pose graph
//   DATA_DIR/vo/<environment>-<n>/odometry.{kitti,tum}    chained odometry
//   DATA_DIR/vo/<environment>-<n>/vo.json                 counts, timing, ATE
// n counts the robot's deployments. The replay memory lives for one process:
// the weights carry what the generalizer learned to the next deployment.
#ifndef FLEETMEM_CLIENTS_ROBOT_VO_VO_DEPLOYMENT_H_
#define FLEETMEM_CLIENTS_ROBOT_VO_VO_DEPLOYMENT_H_

#include <string>

#include "absl/status/statusor.h"
#include "clients/robot/vo/continual_vo.h"

namespace fleetmem::vo {

struct VoDeploymentOptions {
  std::string sequence_dir;   // image_l/, calib.txt, poses.txt (optional)
  std::string data_dir;       // the robot's state
  std::string initial_model;  // used when DATA_DIR/vo-weights.pt is absent
  std::string environment;    // default: the sequence folder's name
  VoMethod method = VoMethod::kClSlam;
  ContinualVoOptions vo;
};

struct VoDeploymentReport {
  std::string out_dir;
  DeploymentResult result;
  // ATE (SE(3), m) against the sequence's poses.txt; < 0 without one.
  double ate_se3_m = -1.0;
};

// NOT_FOUND without weights or sequence; the robot's weights are replaced
// only after the whole deployment succeeded.
absl::StatusOr<VoDeploymentReport> RunVoDeployment(
    const VoDeploymentOptions& options,
    const std::function<void(size_t, size_t)>& progress = {});

}  // namespace fleetmem::vo

#endif  // FLEETMEM_CLIENTS_ROBOT_VO_VO_DEPLOYMENT_H_
