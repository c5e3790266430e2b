// Trajectories as the established evaluation tools read and write them:
//
//   KITTI  one pose per line, the 3x4 matrix [R|t] row by row (12 numbers),
//          pose of frame i in frame 0; no timestamps (frame i has time i).
//   TUM    `timestamp x y z qx qy qz qw` per line, '#' starts a comment.
//
// fleetmem-robot --slam writes TUM (timestamps in seconds), so its output
// reads back with the same functions.
#ifndef FLEETMEM_CLIENTS_ROBOT_SLAM_TRAJECTORY_H_
#define FLEETMEM_CLIENTS_ROBOT_SLAM_TRAJECTORY_H_

#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "Eigen/Geometry"
#include "absl/status/statusor.h"

namespace fleetmem::slam {

struct StampedPose {
  double time_s = 0.0;
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
};
using Trajectory = std::vector<StampedPose>;

enum class TrajectoryFormat { kKitti, kTum };

// "kitti" / "tum"; INVALID_ARGUMENT otherwise.
absl::StatusOr<TrajectoryFormat> ParseTrajectoryFormat(std::string_view name);

// The format of a file's text, from its first data line: 12 numbers =
// KITTI, 8 = TUM. INVALID_ARGUMENT naming `name` otherwise.
absl::StatusOr<TrajectoryFormat> DetectTrajectoryFormat(
    std::string_view text, const std::string& name);

// Parses `text`. INVALID_ARGUMENT naming `name` and the line for a line with
// the wrong number of fields, a value that is not a finite number, a
// quaternion that is not unit length within 1e-3 (it is normalised
// otherwise), a rotation that is not orthonormal within 1e-3, or TUM
// timestamps that do not increase; NOT_FOUND if the text holds no pose.
absl::StatusOr<Trajectory> ParseTrajectory(std::string_view text,
                                           TrajectoryFormat format,
                                           const std::string& name);

// Reads and parses `path`; `format` is detected when not given (and
// reported through `used` when that is not null). NOT_FOUND if the file
// cannot be read.
absl::StatusOr<Trajectory> ReadTrajectoryFile(
    const std::string& path, std::optional<TrajectoryFormat> format,
    TrajectoryFormat* used = nullptr);

// The text of a trajectory in `format` (full double precision).
std::string FormatTrajectory(const Trajectory& trajectory,
                             TrajectoryFormat format);

// The lines of a text file that hold data, with their 1-based numbers:
// whitespace stripped, empty lines and '#' comments left out. The views
// point into `text`.
struct DataLine {
  int number = 0;
  std::string_view text;
};
std::vector<DataLine> DataLines(std::string_view text);

// The pose of a planar robot at (x, y, yaw) as a 3-D pose (z = 0, rotation
// about z), and back (the yaw of the rotation's x axis in the plane).
Eigen::Isometry3d PlanarPose(double x, double y, double yaw);
double YawOf(const Eigen::Isometry3d& pose);

}  // namespace fleetmem::slam

#endif  // FLEETMEM_CLIENTS_ROBOT_SLAM_TRAJECTORY_H_
