// Trajectory error metrics, computed as the established tools compute them
// (docs/slam.md checks every figure against an independent numpy script):
//
//   ATE   absolute trajectory error: positions of the estimate after
//         Umeyama alignment (SE(3) or Sim(3)) to the reference, as evo_ape
//         -a / -as does (Umeyama 1991).
//   RPE   relative pose error of pose pairs, no alignment: error pose
//         E = (Q_i^-1 Q_j)^-1 (P_i^-1 P_j) (Sturm et al. 2012), pairs formed
//         as evo_rpe forms them by default: every `delta` frames, or, for a
//         distance, each pair starting where the previous one ended and
//         ending at the first pose at least `delta` metres of path further.
//   KITTI t_err (%) and r_err (deg / 100 m) over all sub-sequences of
//         100, 200, ..., 800 m of the reference's path, starting every 10
//         frames (Geiger et al. 2012, the odometry devkit).
//   Relations  the Freiburg metric for 2-D SLAM (Kuemmerle et al. 2009):
//         over hand-checked relative poses between scan times, the error
//         of the estimate's relative pose.
//   AQ/RQ CL-SLAM's adaptation and retention quality over a table of
//         deployments (Voedisch et al. 2022, Eqs. 3-6).
#ifndef FLEETMEM_CLIENTS_ROBOT_SLAM_TRAJECTORY_METRICS_H_
#define FLEETMEM_CLIENTS_ROBOT_SLAM_TRAJECTORY_METRICS_H_

#include <string>
#include <string_view>
#include <vector>

#include "Eigen/Core"
#include "Eigen/Geometry"
#include "absl/status/statusor.h"
#include "clients/robot/slam/trajectory.h"

namespace fleetmem::slam {

// Summary of a list of errors. std is the population standard deviation
// (numpy's default, evo's), rmse = sqrt(mean of squares).
struct ErrorStats {
  size_t count = 0;
  double rmse = 0.0;
  double mean = 0.0;
  double median = 0.0;
  double std = 0.0;
  double min = 0.0;
  double max = 0.0;
};
ErrorStats Summarize(std::vector<double> errors);

// x -> scale * rotation * x + translation.
struct Similarity {
  Eigen::Matrix3d rotation = Eigen::Matrix3d::Identity();
  Eigen::Vector3d translation = Eigen::Vector3d::Zero();
  double scale = 1.0;
};

// The similarity (scale fixed to 1 unless `with_scale`) that maps `source`
// onto `target` in the least-squares sense (Umeyama 1991). Both 3 x N, N
// >= 3; INVALID_ARGUMENT for fewer points, different sizes, or points that
// are all the same (no scale can be found).
absl::StatusOr<Similarity> Umeyama(const Eigen::Matrix3Xd& source,
                                   const Eigen::Matrix3Xd& target,
                                   bool with_scale);

// Index pairs (reference, estimate) of poses at the same time. Like evo's
// association: the shorter trajectory's poses are matched, each with the
// nearest-in-time pose of the longer one, kept if within `max_diff_s`.
struct Association {
  std::vector<size_t> reference;
  std::vector<size_t> estimate;
};
Association AssociateByTime(const Trajectory& reference,
                            const Trajectory& estimate, double max_diff_s);

// The two trajectories reduced to associated poses, in order. KITTI files
// have no time: they must have the same length and are paired by index
// (`by_index`). INVALID_ARGUMENT if the lengths differ (by index) or fewer
// than 3 poses associate.
absl::StatusOr<std::pair<Trajectory, Trajectory>> AssociatedPoses(
    const Trajectory& reference, const Trajectory& estimate, bool by_index,
    double max_diff_s);

enum class Alignment { kNone, kSe3, kSim3 };
absl::StatusOr<Alignment> ParseAlignment(std::string_view name);

struct AteResult {
  ErrorStats translation_m;
  Similarity alignment;
};
// ATE of associated poses (equal lengths).
absl::StatusOr<AteResult> AbsoluteTrajectoryError(const Trajectory& reference,
                                                  const Trajectory& estimate,
                                                  Alignment alignment);

struct RpeOptions {
  // > 0: pairs by path length in metres; otherwise every delta_frames.
  double delta_m = 0.0;
  // Frame delta when delta_m <= 0 (evo's default: 1).
  int delta_frames = 1;
  // Form the pairs on the reference's path instead of the estimate's (evo's
  // --pairs_from_reference; its default forms them on the estimate).
  bool pairs_from_reference = false;
};
struct RpeResult {
  ErrorStats translation_m;
  ErrorStats rotation_deg;
  std::vector<std::pair<size_t, size_t>> pairs;
};
// RPE of associated poses. INVALID_ARGUMENT if no pair can be formed.
absl::StatusOr<RpeResult> RelativePoseError(const Trajectory& reference,
                                            const Trajectory& estimate,
                                            const RpeOptions& options);

struct KittiOdometryResult {
  double t_err_percent = 0.0;
  double r_err_deg_per_100m = 0.0;
  // Sub-sequences evaluated (0 when the path is shorter than the shortest
  // length: then the errors are not defined and are left at 0).
  size_t segments = 0;
};
// The sub-sequences: the devkit's 100..800 m every 10 frames by default.
// Shorter lengths give the same definition on paths under 100 m (the
// continual-VO clips); they are not comparable with KITTI's tables.
struct KittiSegments {
  std::vector<double> lengths_m = {100, 200, 300, 400, 500, 600, 700, 800};
  int step_frames = 10;
};
KittiOdometryResult KittiOdometryError(const Trajectory& reference,
                                       const Trajectory& estimate,
                                       const KittiSegments& segments = {});

// One line of a Freiburg relations file: `t1 t2 x y z roll pitch yaw`, the
// pose of the scan at t2 in the frame of the scan at t1.
struct Relation {
  double t1 = 0.0;
  double t2 = 0.0;
  double x = 0.0;
  double y = 0.0;
  double yaw = 0.0;
};
absl::StatusOr<std::vector<Relation>> ParseRelations(std::string_view text,
                                                     const std::string& name);

struct RelationsResult {
  // Absolute translational (m) and rotational (deg) errors.
  ErrorStats translation_m;
  ErrorStats rotation_deg;
  // Means and population std of the squared errors (m^2, deg^2), the
  // other half of Kuemmerle et al.'s tables.
  double translation_sq_mean = 0.0;
  double translation_sq_std = 0.0;
  double rotation_sq_mean = 0.0;
  double rotation_sq_std = 0.0;
  // Relations whose scan times the estimate lacks (left out).
  size_t missing = 0;
};
// The estimate's pose at a relation's time is its pose with the nearest
// time, within `max_diff_s`. INVALID_ARGUMENT if no relation can be scored.
absl::StatusOr<RelationsResult> RelationsError(
    const Trajectory& estimate, const std::vector<Relation>& relations,
    double max_diff_s);

// A deployment sequence of CL-SLAM's protocol: the scenes in order (the
// first initialises the method, e.g. "ct" for Cityscapes pre-training), and
// the errors on the last scene. A scene's environment is its name without
// trailing digits ("k1" and "k2" are both KITTI, "k").
struct Deployment {
  std::vector<std::string> scenes;
  double t_err_percent = 0.0;
  double r_err_deg_per_100m = 0.0;
};
// CSV with a header naming `sequence`, `t_err` and `r_err`; the sequence's
// scenes are separated by '>' ("ct>k1>r1").
absl::StatusOr<std::vector<Deployment>> ParseDeployments(
    std::string_view text, const std::string& name);

struct ContinualScores {
  double aq_trans = 0.0;
  double aq_rot = 0.0;
  double rq_trans = 0.0;
  double rq_rot = 0.0;
  size_t aq_sequences = 0;
  size_t rq_pairs = 0;
};
// Base metrics t^ = max(0, 1 - t_err / 100) and r^ = 1 - r_err / 180
// (Eq. 3). AQ: their mean over the sequences whose last scene is in an
// environment not seen earlier in the sequence (the initialisation's aside;
// Eq. 4). RQ: the mean over the sequences whose last scene revisits an
// environment right after scenes of other environments, of the metric minus
// the metric of the same sequence without those intermediate scenes
// (Eq. 6); that sequence must be in the table. INVALID_ARGUMENT when a
// needed sequence is missing or a sequence appears twice.
absl::StatusOr<ContinualScores> ScoreDeployments(
    const std::vector<Deployment>& deployments);

}  // namespace fleetmem::slam

#endif  // FLEETMEM_CLIENTS_ROBOT_SLAM_TRAJECTORY_METRICS_H_
