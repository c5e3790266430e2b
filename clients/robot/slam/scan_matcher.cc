#include "clients/robot/slam/scan_matcher.h"

#include <algorithm>
#include <cmath>
#include <cstring>

#include "Eigen/Eigenvalues"
#include "absl/strings/str_format.h"

namespace fleetmem::slam {
namespace {

constexpr double kPi = 3.14159265358979323846;
// Neighbourhood of a reference point's line normal.
constexpr double kNormalRadius = 0.3;

}  // namespace

Points2 ScanPoints(const robot::LaserScan& scan, double max_range_m) {
  Points2 points;
  const size_t n = scan.ranges.size();
  if (n == 0) return points;
  const double step = n > 1 ? scan.field_of_view / (n - 1) : 0.0;
  for (size_t i = 0; i < n; ++i) {
    const double r = scan.ranges[i];
    if (!(r > 0.0) || r >= scan.max_range || r > max_range_m) continue;
    const double bearing = -scan.field_of_view / 2 + step * i;
    points.emplace_back(r * std::cos(bearing), r * std::sin(bearing));
  }
  return points;
}

Points2 Transform(const Points2& points, const Pose2& pose) {
  const double c = std::cos(pose.yaw), s = std::sin(pose.yaw);
  Points2 out;
  out.reserve(points.size());
  for (const Eigen::Vector2d& p : points) {
    out.emplace_back(pose.x + c * p.x() - s * p.y(),
                     pose.y + s * p.x() + c * p.y());
  }
  return out;
}

long ScanMatcher::CellKey(int cx, int cy) const {
  const uint64_t key =
      (static_cast<uint64_t>(static_cast<uint32_t>(cx)) << 32) |
      static_cast<uint32_t>(cy);
  return static_cast<long>(key);
}

ScanMatcher::ScanMatcher(Points2 reference, const ScanMatchOptions& options)
    : options_(options), points_(std::move(reference)) {
  for (size_t i = 0; i < points_.size(); ++i) {
    grid_[CellKey(static_cast<int>(std::floor(points_[i].x() / cell_)),
                  static_cast<int>(std::floor(points_[i].y() / cell_)))]
        .push_back(static_cast<int>(i));
  }
  normals_.assign(points_.size(), Eigen::Vector2d::Zero());
  has_normal_.assign(points_.size(), false);
  for (size_t i = 0; i < points_.size(); ++i) {
    const Eigen::Vector2d& p = points_[i];
    Eigen::Vector2d mean = Eigen::Vector2d::Zero();
    std::vector<int> near;
    const int cx = static_cast<int>(std::floor(p.x() / cell_));
    const int cy = static_cast<int>(std::floor(p.y() / cell_));
    for (int dx = -1; dx <= 1; ++dx) {
      for (int dy = -1; dy <= 1; ++dy) {
        auto it = grid_.find(CellKey(cx + dx, cy + dy));
        if (it == grid_.end()) continue;
        for (int j : it->second) {
          if ((points_[j] - p).norm() <= kNormalRadius) {
            near.push_back(j);
            mean += points_[j];
          }
        }
      }
    }
    if (near.size() < 3) continue;
    mean /= static_cast<double>(near.size());
    Eigen::Matrix2d cov = Eigen::Matrix2d::Zero();
    for (int j : near) {
      const Eigen::Vector2d d = points_[j] - mean;
      cov += d * d.transpose();
    }
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d> eig(cov);
    // A line: one direction dominates.
    if (eig.eigenvalues()(0) > 0.25 * eig.eigenvalues()(1)) continue;
    normals_[i] = eig.eigenvectors().col(0).normalized();
    has_normal_[i] = true;
  }
}

int ScanMatcher::Nearest(const Eigen::Vector2d& p, double radius) const {
  const int reach = static_cast<int>(std::ceil(radius / cell_));
  const int cx = static_cast<int>(std::floor(p.x() / cell_));
  const int cy = static_cast<int>(std::floor(p.y() / cell_));
  int best = -1;
  double best_d2 = radius * radius;
  for (int dx = -reach; dx <= reach; ++dx) {
    for (int dy = -reach; dy <= reach; ++dy) {
      auto it = grid_.find(CellKey(cx + dx, cy + dy));
      if (it == grid_.end()) continue;
      for (int j : it->second) {
        const double d2 = (points_[j] - p).squaredNorm();
        if (d2 < best_d2) {
          best_d2 = d2;
          best = j;
        }
      }
    }
  }
  return best;
}

ScanMatch ScanMatcher::Match(const Points2& scan, const Pose2& initial) const {
  ScanMatch result;
  result.pose = initial;
  if (scan.empty() || points_.empty()) return result;
  Eigen::Vector3d x(initial.x, initial.y, initial.yaw);
  for (int it = 0; it < options_.max_iterations; ++it) {
    const double shrink =
        options_.max_iterations > 1
            ? static_cast<double>(it) / (options_.max_iterations - 1)
            : 1.0;
    const double radius =
        options_.max_correspondence_m +
        (options_.final_correspondence_m - options_.max_correspondence_m) *
            std::min(1.0, 2.0 * shrink);
    const double c = std::cos(x(2)), s = std::sin(x(2));
    Eigen::Matrix3d h = Eigen::Matrix3d::Zero();
    Eigen::Vector3d g = Eigen::Vector3d::Zero();
    int used = 0;
    for (const Eigen::Vector2d& q : scan) {
      const Eigen::Vector2d rq(c * q.x() - s * q.y(), s * q.x() + c * q.y());
      const Eigen::Vector2d w = rq + x.head<2>();
      const int j = Nearest(w, radius);
      if (j < 0 || !has_normal_[j]) continue;
      const Eigen::Vector2d& n = normals_[j];
      const double e = n.dot(w - points_[j]);
      const Eigen::Vector3d jac(n.x(), n.y(),
                                n.dot(Eigen::Vector2d(-rq.y(), rq.x())));
      // Huber weight on the residual (robust to a few wrong pairs).
      const double k = 0.1;
      const double weight = std::abs(e) <= k ? 1.0 : k / std::abs(e);
      h += weight * jac * jac.transpose();
      g += weight * jac * e;
      ++used;
    }
    result.iterations = it + 1;
    if (used < 10) break;
    h += 1e-6 * Eigen::Matrix3d::Identity();
    const Eigen::Vector3d delta = -h.ldlt().solve(g);
    x += delta;
    x(2) = NormalizeAngle(x(2));
    if (delta.head<2>().norm() < 1e-5 && std::abs(delta(2)) < 1e-6 &&
        shrink >= 0.5) {
      break;
    }
  }
  result.pose = Pose2{x(0), x(1), x(2)};
  // Score at the final correspondence distance.
  const Points2 moved = Transform(scan, result.pose);
  int inliers = 0;
  double sum_sq = 0.0;
  Eigen::Matrix2d normal_matrix = Eigen::Matrix2d::Zero();
  for (const Eigen::Vector2d& w : moved) {
    const int j = Nearest(w, options_.final_correspondence_m);
    if (j < 0) continue;
    ++inliers;
    if (has_normal_[j]) normal_matrix += normals_[j] * normals_[j].transpose();
    const double e = has_normal_[j] ? normals_[j].dot(w - points_[j])
                                    : (w - points_[j]).norm();
    sum_sq += e * e;
  }
  result.inlier_ratio = static_cast<double>(inliers) / scan.size();
  result.rms_m = inliers > 0 ? std::sqrt(sum_sq / inliers) : 0.0;
  const Eigen::Vector2d eig =
      Eigen::SelfAdjointEigenSolver<Eigen::Matrix2d>(normal_matrix)
          .eigenvalues();
  result.conditioning = eig(1) > 0.0 ? eig(0) / eig(1) : 0.0;
  result.accepted = result.inlier_ratio >= options_.min_inlier_ratio &&
                    result.rms_m <= options_.max_rms_m &&
                    result.conditioning >= options_.min_conditioning;
  return result;
}

ScanMatch ScanMatcher::MatchBest(const Points2& scan,
                                 const std::vector<Pose2>& initials) const {
  ScanMatch best;
  bool first = true;
  for (const Pose2& initial : initials) {
    ScanMatch m = Match(scan, initial);
    if (first || m.inlier_ratio > best.inlier_ratio + 1e-9 ||
        (std::abs(m.inlier_ratio - best.inlier_ratio) <= 1e-9 &&
         m.rms_m < best.rms_m)) {
      best = m;
      first = false;
    }
  }
  return best;
}

std::vector<Pose2> InitialGuesses(const Pose2& center, double yaw_span,
                                  double yaw_step, double xy_span,
                                  double xy_step) {
  std::vector<Pose2> out;
  std::vector<double> yaws;
  if (yaw_span >= kPi) {
    for (double a = 0.0; a < 2.0 * kPi - 1e-9; a += yaw_step) yaws.push_back(a);
  } else {
    yaws.push_back(0.0);
    for (double a = yaw_step; a <= yaw_span + 1e-9; a += yaw_step) {
      yaws.push_back(a);
      yaws.push_back(-a);
    }
  }
  std::vector<double> offsets = {0.0};
  for (double d = xy_step; xy_step > 0 && d <= xy_span + 1e-9; d += xy_step) {
    offsets.push_back(d);
    offsets.push_back(-d);
  }
  for (double dyaw : yaws) {
    for (double dx : offsets) {
      for (double dy : offsets) {
        out.push_back(Pose2{center.x + dx, center.y + dy,
                            NormalizeAngle(center.yaw + dyaw)});
      }
    }
  }
  return out;
}

std::string EncodeScan(const robot::LaserScan& scan) {
  std::string out;
  const uint16_t n =
      static_cast<uint16_t>(std::min<size_t>(scan.ranges.size(), 65535));
  const float fov = static_cast<float>(scan.field_of_view);
  out.resize(2 + 4 + 2 * n);
  std::memcpy(out.data(), &n, 2);
  std::memcpy(out.data() + 2, &fov, 4);
  for (uint16_t i = 0; i < n; ++i) {
    const float r = scan.ranges[i];
    uint16_t mm = 0;
    if (r > 0.0f && r < scan.max_range && r < 65.0f) {
      mm = static_cast<uint16_t>(std::lround(r * 1000.0f));
    }
    std::memcpy(out.data() + 6 + 2 * i, &mm, 2);
  }
  return out;
}

absl::StatusOr<robot::LaserScan> DecodeScan(std::string_view bytes) {
  if (bytes.size() < 6) {
    return absl::InvalidArgumentError("scan attachment shorter than 6 bytes");
  }
  uint16_t n = 0;
  float fov = 0.0f;
  std::memcpy(&n, bytes.data(), 2);
  std::memcpy(&fov, bytes.data() + 2, 4);
  if (bytes.size() != 6 + 2 * static_cast<size_t>(n) || n == 0 ||
      !(fov > 0.0f && fov <= 2.0f * kPi)) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "scan attachment of %d bytes does not hold a scan", bytes.size()));
  }
  robot::LaserScan scan;
  scan.field_of_view = fov;
  scan.max_range = 65.536f;
  scan.ranges.resize(n);
  for (uint16_t i = 0; i < n; ++i) {
    uint16_t mm = 0;
    std::memcpy(&mm, bytes.data() + 6 + 2 * i, 2);
    scan.ranges[i] = mm / 1000.0f;
  }
  return scan;
}

}  // namespace fleetmem::slam
