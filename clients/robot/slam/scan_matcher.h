// 2-D scan matching: point-to-line ICP (Censi 2008's metric, solved with
// Gauss-Newton on the linearised rotation) of a scan against a reference
// point set, from one or several initial guesses. It is what turns a loop
// candidate from place recognition into a relative pose or a rejection,
// and what refines wheel odometry between keyframes.
#ifndef FLEETMEM_CLIENTS_ROBOT_SLAM_SCAN_MATCHER_H_
#define FLEETMEM_CLIENTS_ROBOT_SLAM_SCAN_MATCHER_H_

#include <string>
#include <string_view>
#include <unordered_map>
#include <vector>

#include "Eigen/Core"
#include "absl/status/statusor.h"
#include "clients/robot/sensing/observation.h"
#include "clients/robot/slam/pose_graph.h"

namespace fleetmem::slam {

using Points2 = std::vector<Eigen::Vector2d>;

// The scan's returns as points in the sensor frame (x forward), leaving out
// no-returns and ranges beyond `max_range_m`.
Points2 ScanPoints(const robot::LaserScan& scan, double max_range_m);
// `points` moved by `pose`.
Points2 Transform(const Points2& points, const Pose2& pose);

struct ScanMatchOptions {
  int max_iterations = 40;
  // Correspondences farther apart than this are ignored (metres); the
  // distance shrinks to `final_correspondence_m` over the iterations.
  double max_correspondence_m = 1.0;
  double final_correspondence_m = 0.25;
  // A match is accepted when at least this share of the scan's points has
  // a correspondence within final_correspondence_m and their point-to-line
  // RMS is at most max_rms_m.
  double min_inlier_ratio = 0.6;
  double max_rms_m = 0.08;
  // ... and when the match pins the translation down in every direction:
  // the smaller eigenvalue of the point-to-line normal matrix's translation
  // block is at least this share of the larger. A corridor constrains only
  // across it; ICP can slide along it to any place that looks the same.
  double min_conditioning = 0.0;
};

struct ScanMatch {
  // Pose of the scan in the reference's frame.
  Pose2 pose;
  double inlier_ratio = 0.0;
  double rms_m = 0.0;
  // lambda_min / lambda_max of the translation block (1: well constrained).
  double conditioning = 0.0;
  int iterations = 0;
  bool accepted = false;
};

// Thread-compatible. Keeps the reference's points in a grid for nearest-
// neighbour lookups and their line normals (from neighbours within 0.3 m).
class ScanMatcher {
 public:
  explicit ScanMatcher(Points2 reference, const ScanMatchOptions& options = {});

  // ICP of `scan` (sensor-frame points) from `initial`.
  ScanMatch Match(const Points2& scan, const Pose2& initial) const;
  // The best-scoring of Match from each initial guess (by inlier ratio,
  // then RMS).
  ScanMatch MatchBest(const Points2& scan,
                      const std::vector<Pose2>& initials) const;

  size_t size() const { return points_.size(); }

 private:
  // Index of the nearest reference point within `radius`, or -1.
  int Nearest(const Eigen::Vector2d& p, double radius) const;
  long CellKey(int cx, int cy) const;

  ScanMatchOptions options_;
  Points2 points_;
  std::vector<Eigen::Vector2d> normals_;
  std::vector<bool> has_normal_;
  double cell_ = 0.5;
  // cell key -> point indices.
  std::unordered_map<long, std::vector<int>> grid_;
};

// Initial guesses around `center`: yaw offsets every `yaw_step` radians
// within +-yaw_span (the full circle when yaw_span >= pi), each combined
// with translation offsets on a square grid of `xy_step` within +-xy_span.
std::vector<Pose2> InitialGuesses(const Pose2& center, double yaw_span,
                                  double yaw_step, double xy_span,
                                  double xy_step);

// A scan as compact bytes and back, for a keyframe trace's attachment:
// little-endian uint16 count, float32 field of view, then one uint16 per
// beam in millimetres (0 = no return). INVALID_ARGUMENT for bytes that do
// not hold a scan.
std::string EncodeScan(const robot::LaserScan& scan);
absl::StatusOr<robot::LaserScan> DecodeScan(std::string_view bytes);

}  // namespace fleetmem::slam

#endif  // FLEETMEM_CLIENTS_ROBOT_SLAM_SCAN_MATCHER_H_
