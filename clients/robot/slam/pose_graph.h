// Pose graphs of odometry and loop edges, optimised with Ceres
// (CL-SLAM Sec. 3.3; Grisetti et al. 2010's tutorial formulation):
//
//   minimise  sum_odometry ||r_ij||^2  +  sum_loop rho(||r_ij||^2)
//   r_ij = S_ij * (z_ij^-1 (x_i^-1 x_j))   (as a minimal vector)
//
// with S_ij^T S_ij = Omega_ij, the edge's information matrix, and rho the
// Cauchy loss on loop edges: a wrong loop (a place-recognition false
// positive that passed the geometric check) pulls the graph with a force
// that falls off with its residual instead of growing with it. After the
// solve, loop edges whose whitened residual still exceeds
// `outlier_sigma` are switched off and the graph solved again, so that a
// rejected loop leaves no trace in the map.
//
// Re-optimisation is incremental in the practical sense: every Optimize
// starts from the current estimate (the previous solution, plus new nodes
// placed by odometry), so adding a loop costs a few iterations.
//
// Two graphs: SE(2) (x, y, yaw; the laser robots) and SE(3) (position and
// unit quaternion). The first node is held fixed (the gauge).
#ifndef FLEETMEM_CLIENTS_ROBOT_SLAM_POSE_GRAPH_H_
#define FLEETMEM_CLIENTS_ROBOT_SLAM_POSE_GRAPH_H_

#include <cstddef>
#include <vector>

#include "Eigen/Core"
#include "Eigen/Geometry"
#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fleetmem::slam {

struct Pose2 {
  double x = 0.0;
  double y = 0.0;
  double yaw = 0.0;
};
// a * b and a^-1 * b for planar poses.
Pose2 Compose(const Pose2& a, const Pose2& b);
Pose2 Between(const Pose2& a, const Pose2& b);
// Wraps an angle to (-pi, pi].
double NormalizeAngle(double a);

enum class EdgeKind { kOdometry, kLoop };

struct PoseGraphOptions {
  // Scale of the Cauchy loss on loop edges, in standard deviations of the
  // edge (whitened units): residuals well beyond it count less and less.
  double loop_loss_scale = 3.0;
  // Graduated non-convexity: each Optimize solves first with the loop loss
  // scale multiplied by gnc_factor^gnc_stages, then divides it by
  // gnc_factor per stage down to loop_loss_scale. A loop that closes after
  // long drift starts many sigmas off; a tight loss from the start would
  // treat it as an outlier, a wide one first lets the consistent loops pull
  // the graph into place. 0 stages: one solve at loop_loss_scale.
  int gnc_stages = 2;
  double gnc_factor = 10.0;
  // After a solve, loop edges whose whitened residual norm is above this
  // are disabled and the graph is solved again (<= 0: never). Loose on
  // purpose: a wrong loop is metres or tens of degrees off (hundreds of
  // sigmas), while correct loops can sit several sigmas off when the
  // information matrices are optimistic.
  double outlier_sigma = 10.0;
  // Levenberg-Marquardt iterations per solve.
  int max_iterations = 100;
};

struct SolveReport {
  int iterations = 0;
  double initial_cost = 0.0;
  double final_cost = 0.0;
  // Loop edges switched off by this solve (indices into the edges).
  std::vector<size_t> rejected_loops;
};

// Thread-compatible.
template <typename PoseT, int kDof>
class PoseGraph {
 public:
  using Information = Eigen::Matrix<double, kDof, kDof>;
  struct Edge {
    size_t from = 0;
    size_t to = 0;
    PoseT measurement;  // pose of `to` in the frame of `from`
    Information information = Information::Identity();
    EdgeKind kind = EdgeKind::kOdometry;
    bool active = true;
  };

  explicit PoseGraph(const PoseGraphOptions& options = {})
      : options_(options) {}

  // A new node at `initial`; returns its id (0, 1, ...).
  size_t AddNode(const PoseT& initial);
  // INVALID_ARGUMENT for an unknown node, from == to, or an information
  // matrix that is not symmetric positive definite; the graph is unchanged.
  absl::Status AddEdge(size_t from, size_t to, const PoseT& measurement,
                       const Information& information, EdgeKind kind);
  // Solves from the current estimate. INVALID_ARGUMENT for an empty graph,
  // INTERNAL if Ceres reports a failure (the estimate is then unchanged).
  absl::StatusOr<SolveReport> Optimize();

  size_t num_nodes() const { return poses_.size(); }
  const PoseT& pose(size_t id) const { return poses_[id]; }
  // Every node's pose, by id.
  const std::vector<PoseT>& poses() const { return poses_; }
  const std::vector<Edge>& edges() const { return edges_; }
  // Whitened residual norm of an edge at the current estimate.
  double WhitenedResidual(size_t edge) const;

 private:
  // One Ceres solve with the given loop loss scale.
  absl::Status Solve(double loss_scale, SolveReport& report);

  PoseGraphOptions options_;
  std::vector<PoseT> poses_;
  std::vector<Edge> edges_;
};

using PoseGraph2d = PoseGraph<Pose2, 3>;
using PoseGraph3d = PoseGraph<Eigen::Isometry3d, 6>;

}  // namespace fleetmem::slam

#endif  // FLEETMEM_CLIENTS_ROBOT_SLAM_POSE_GRAPH_H_
