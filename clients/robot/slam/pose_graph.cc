#include "clients/robot/slam/pose_graph.h"

#include <cmath>
#include <memory>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "ceres/ceres.h"

namespace fleetmem::slam {
namespace {

constexpr double kPi = 3.14159265358979323846;

template <typename T>
T WrapAngle(const T& a) {
  using std::floor;
  return a - T(2.0 * kPi) * floor((a + T(kPi)) / T(2.0 * kPi));
}

template <int kDof>
Eigen::Matrix<double, kDof, kDof> SqrtInformation(
    const Eigen::Matrix<double, kDof, kDof>& information) {
  // S with S^T S = Omega: the transposed lower Cholesky factor.
  return information.llt().matrixL().transpose();
}

// r = S * minimal(z^-1 (a^-1 b)) for planar poses (x, y, yaw).
struct Se2Residual {
  Pose2 z;
  Eigen::Matrix3d sqrt_information;

  template <typename T>
  bool operator()(const T* a, const T* b, T* residual) const {
    using std::cos;
    using std::sin;
    const T dx = b[0] - a[0];
    const T dy = b[1] - a[1];
    const T ca = cos(a[2]), sa = sin(a[2]);
    const T tx = ca * dx + sa * dy - T(z.x);
    const T ty = -sa * dx + ca * dy - T(z.y);
    const T cz = T(std::cos(z.yaw)), sz = T(std::sin(z.yaw));
    Eigen::Matrix<T, 3, 1> e(cz * tx + sz * ty, -sz * tx + cz * ty,
                             WrapAngle(b[2] - a[2] - T(z.yaw)));
    Eigen::Map<Eigen::Matrix<T, 3, 1>> out(residual);
    out = sqrt_information.cast<T>() * e;
    return true;
  }
};

// r = S * [R_z^T (t_ab - t_z); 2 vec(q_z^-1 q_ab)] for poses as position and
// unit quaternion (x, y, z, w: Eigen's storage order).
struct Se3Residual {
  Eigen::Vector3d z_t;
  Eigen::Quaterniond z_q;
  Eigen::Matrix<double, 6, 6> sqrt_information;

  template <typename T>
  bool operator()(const T* pa, const T* qa, const T* pb, const T* qb,
                  T* residual) const {
    Eigen::Map<const Eigen::Matrix<T, 3, 1>> p_a(pa), p_b(pb);
    Eigen::Map<const Eigen::Quaternion<T>> q_a(qa), q_b(qb);
    const Eigen::Quaternion<T> q_a_inv = q_a.conjugate();
    const Eigen::Quaternion<T> q_ab = q_a_inv * q_b;
    const Eigen::Matrix<T, 3, 1> t_ab = q_a_inv * (p_b - p_a);
    const Eigen::Quaternion<T> z_q_inv = z_q.conjugate().cast<T>();
    Eigen::Matrix<T, 6, 1> e;
    e.template head<3>() = z_q_inv * (t_ab - z_t.cast<T>());
    e.template tail<3>() = T(2.0) * (z_q_inv * q_ab).vec();
    Eigen::Map<Eigen::Matrix<T, 6, 1>> out(residual);
    out = sqrt_information.cast<T>() * e;
    return true;
  }
};

// The parameter blocks of one solve.
struct Se2Blocks {
  std::vector<std::array<double, 3>> poses;
};
struct Se3Blocks {
  std::vector<std::array<double, 3>> positions;
  std::vector<std::array<double, 4>> rotations;
};

// One Levenberg-Marquardt solve; the report gets its iterations and costs.
// INTERNAL if Ceres fails (the parameter blocks are then not to be used).
absl::Status RunSolver(ceres::Problem& problem, int max_iterations,
                       SolveReport& report) {
  ceres::Solver::Options options;
  options.linear_solver_type = ceres::SPARSE_NORMAL_CHOLESKY;
  options.max_num_iterations = max_iterations;
  options.num_threads = 1;
  options.logging_type = ceres::SILENT;
  ceres::Solver::Summary summary;
  ceres::Solve(options, &problem, &summary);
  if (summary.termination_type == ceres::FAILURE) {
    return absl::InternalError(
        absl::StrCat("pose graph solve failed: ", summary.message));
  }
  report.iterations = static_cast<int>(summary.iterations.size());
  report.initial_cost = summary.initial_cost;
  report.final_cost = summary.final_cost;
  return absl::OkStatus();
}

}  // namespace

double NormalizeAngle(double a) { return WrapAngle(a); }

Pose2 Compose(const Pose2& a, const Pose2& b) {
  const double c = std::cos(a.yaw), s = std::sin(a.yaw);
  return Pose2{a.x + c * b.x - s * b.y, a.y + s * b.x + c * b.y,
               NormalizeAngle(a.yaw + b.yaw)};
}

Pose2 Between(const Pose2& a, const Pose2& b) {
  const double c = std::cos(a.yaw), s = std::sin(a.yaw);
  const double dx = b.x - a.x, dy = b.y - a.y;
  return Pose2{c * dx + s * dy, -s * dx + c * dy,
               NormalizeAngle(b.yaw - a.yaw)};
}

template <typename PoseT, int kDof>
size_t PoseGraph<PoseT, kDof>::AddNode(const PoseT& initial) {
  poses_.push_back(initial);
  return poses_.size() - 1;
}

template <typename PoseT, int kDof>
absl::Status PoseGraph<PoseT, kDof>::AddEdge(size_t from, size_t to,
                                             const PoseT& measurement,
                                             const Information& information,
                                             EdgeKind kind) {
  if (from >= poses_.size() || to >= poses_.size()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "edge %d -> %d: the graph has %d nodes", from, to, poses_.size()));
  }
  if (from == to) {
    return absl::InvalidArgumentError(
        absl::StrFormat("edge %d -> %d joins a node to itself", from, to));
  }
  if (!information.allFinite() ||
      !information.isApprox(information.transpose(), 1e-9) ||
      information.llt().info() != Eigen::Success) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "edge %d -> %d: the information matrix is not symmetric positive "
        "definite",
        from, to));
  }
  edges_.push_back(Edge{from, to, measurement, information, kind, true});
  return absl::OkStatus();
}

template <typename PoseT, int kDof>
absl::StatusOr<SolveReport> PoseGraph<PoseT, kDof>::Optimize() {
  if (poses_.empty()) return absl::InvalidArgumentError("empty pose graph");
  SolveReport report;
  double scale =
      options_.loop_loss_scale *
      std::pow(options_.gnc_factor, std::max(0, options_.gnc_stages));
  for (int stage = std::max(0, options_.gnc_stages); stage >= 0; --stage) {
    SolveReport step;
    if (absl::Status s = Solve(scale, step); !s.ok()) return s;
    if (report.iterations == 0) report.initial_cost = step.initial_cost;
    report.iterations += step.iterations;
    report.final_cost = step.final_cost;
    scale /= options_.gnc_factor;
  }
  if (options_.outlier_sigma <= 0) return report;
  for (size_t e = 0; e < edges_.size(); ++e) {
    if (edges_[e].kind == EdgeKind::kLoop && edges_[e].active &&
        WhitenedResidual(e) > options_.outlier_sigma) {
      edges_[e].active = false;
      report.rejected_loops.push_back(e);
    }
  }
  if (!report.rejected_loops.empty()) {
    SolveReport again;
    if (absl::Status s = Solve(options_.loop_loss_scale, again); !s.ok()) {
      return s;
    }
    report.iterations += again.iterations;
    report.final_cost = again.final_cost;
  }
  return report;
}

// --- SE(2) ---------------------------------------------------------------

template <>
absl::Status PoseGraph<Pose2, 3>::Solve(double loss_scale,
                                        SolveReport& report) {
  Se2Blocks blocks;
  for (const Pose2& p : poses_) blocks.poses.push_back({p.x, p.y, p.yaw});
  ceres::Problem problem;
  for (const Edge& e : edges_) {
    if (!e.active) continue;
    auto* cost = new ceres::AutoDiffCostFunction<Se2Residual, 3, 3, 3>(
        new Se2Residual{e.measurement, SqrtInformation<3>(e.information)});
    ceres::LossFunction* loss =
        e.kind == EdgeKind::kLoop ? new ceres::CauchyLoss(loss_scale) : nullptr;
    problem.AddResidualBlock(cost, loss, blocks.poses[e.from].data(),
                             blocks.poses[e.to].data());
  }
  problem.AddParameterBlock(blocks.poses[0].data(), 3);
  problem.SetParameterBlockConstant(blocks.poses[0].data());
  if (absl::Status s = RunSolver(problem, options_.max_iterations, report);
      !s.ok()) {
    return s;
  }
  for (size_t i = 0; i < poses_.size(); ++i) {
    const auto& b = blocks.poses[i];
    poses_[i] = Pose2{b[0], b[1], NormalizeAngle(b[2])};
  }
  return absl::OkStatus();
}

template <>
double PoseGraph<Pose2, 3>::WhitenedResidual(size_t edge) const {
  const Edge& e = edges_[edge];
  const Se2Residual r{e.measurement, SqrtInformation<3>(e.information)};
  const Pose2& a = poses_[e.from];
  const Pose2& b = poses_[e.to];
  const double pa[3] = {a.x, a.y, a.yaw}, pb[3] = {b.x, b.y, b.yaw};
  double out[3];
  r(pa, pb, out);
  return Eigen::Map<Eigen::Vector3d>(out).norm();
}

// --- SE(3) ---------------------------------------------------------------

template <>
absl::Status PoseGraph<Eigen::Isometry3d, 6>::Solve(double loss_scale,
                                                    SolveReport& report) {
  Se3Blocks blocks;
  for (const Eigen::Isometry3d& p : poses_) {
    const Eigen::Quaterniond q(p.linear());
    blocks.positions.push_back(
        {p.translation().x(), p.translation().y(), p.translation().z()});
    blocks.rotations.push_back({q.x(), q.y(), q.z(), q.w()});
  }
  ceres::Problem problem;
  for (const Edge& e : edges_) {
    if (!e.active) continue;
    auto* cost = new ceres::AutoDiffCostFunction<Se3Residual, 6, 3, 4, 3, 4>(
        new Se3Residual{e.measurement.translation(),
                        Eigen::Quaterniond(e.measurement.linear()),
                        SqrtInformation<6>(e.information)});
    ceres::LossFunction* loss =
        e.kind == EdgeKind::kLoop ? new ceres::CauchyLoss(loss_scale) : nullptr;
    problem.AddResidualBlock(cost, loss, blocks.positions[e.from].data(),
                             blocks.rotations[e.from].data(),
                             blocks.positions[e.to].data(),
                             blocks.rotations[e.to].data());
  }
  for (size_t i = 0; i < poses_.size(); ++i) {
    problem.AddParameterBlock(blocks.positions[i].data(), 3);
    problem.AddParameterBlock(blocks.rotations[i].data(), 4,
                              new ceres::EigenQuaternionManifold);
  }
  problem.SetParameterBlockConstant(blocks.positions[0].data());
  problem.SetParameterBlockConstant(blocks.rotations[0].data());
  if (absl::Status s = RunSolver(problem, options_.max_iterations, report);
      !s.ok()) {
    return s;
  }
  for (size_t i = 0; i < poses_.size(); ++i) {
    const auto& t = blocks.positions[i];
    const auto& r = blocks.rotations[i];
    Eigen::Isometry3d p = Eigen::Isometry3d::Identity();
    p.linear() = Eigen::Quaterniond(r[3], r[0], r[1], r[2])
                     .normalized()
                     .toRotationMatrix();
    p.translation() << t[0], t[1], t[2];
    poses_[i] = p;
  }
  return absl::OkStatus();
}

template <>
double PoseGraph<Eigen::Isometry3d, 6>::WhitenedResidual(size_t edge) const {
  const Edge& e = edges_[edge];
  const Se3Residual r{e.measurement.translation(),
                      Eigen::Quaterniond(e.measurement.linear()),
                      SqrtInformation<6>(e.information)};
  const Eigen::Isometry3d& a = poses_[e.from];
  const Eigen::Isometry3d& b = poses_[e.to];
  const Eigen::Quaterniond qa(a.linear()), qb(b.linear());
  const double pa[3] = {a.translation().x(), a.translation().y(),
                        a.translation().z()};
  const double pb[3] = {b.translation().x(), b.translation().y(),
                        b.translation().z()};
  const double ra[4] = {qa.x(), qa.y(), qa.z(), qa.w()};
  const double rb[4] = {qb.x(), qb.y(), qb.z(), qb.w()};
  double out[6];
  r(pa, ra, pb, rb, out);
  return Eigen::Map<Eigen::Matrix<double, 6, 1>>(out).norm();
}

template class PoseGraph<Pose2, 3>;
template class PoseGraph<Eigen::Isometry3d, 6>;

}  // namespace fleetmem::slam
