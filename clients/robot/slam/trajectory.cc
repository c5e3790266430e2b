#include "clients/robot/slam/trajectory.h"

#include <cmath>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "services/common/files.h"

namespace fleetmem::slam {
namespace {

constexpr double kUnitTolerance = 1e-3;

// The numbers of one line, or an error naming the line.
absl::StatusOr<std::vector<double>> LineNumbers(absl::string_view line,
                                                const std::string& where) {
  std::vector<double> numbers;
  for (absl::string_view field :
       absl::StrSplit(line, absl::ByAnyChar(" \t,"), absl::SkipEmpty())) {
    double value = 0.0;
    if (!absl::SimpleAtod(field, &value) || !std::isfinite(value)) {
      return absl::InvalidArgumentError(
          absl::StrCat(where, ": '", field, "' is not a finite number"));
    }
    numbers.push_back(value);
  }
  return numbers;
}

}  // namespace

std::vector<DataLine> DataLines(std::string_view text) {
  std::vector<DataLine> out;
  int number = 0;
  for (absl::string_view line :
       absl::StrSplit(absl::string_view(text.data(), text.size()), '\n')) {
    ++number;
    line = absl::StripAsciiWhitespace(line);
    if (line.empty() || line.front() == '#') continue;
    out.push_back(DataLine{number, std::string_view(line.data(), line.size())});
  }
  return out;
}

absl::StatusOr<TrajectoryFormat> ParseTrajectoryFormat(std::string_view name) {
  if (name == "kitti") return TrajectoryFormat::kKitti;
  if (name == "tum") return TrajectoryFormat::kTum;
  return absl::InvalidArgumentError(absl::StrCat(
      "unknown trajectory format '", std::string(name), "' (kitti, tum)"));
}

absl::StatusOr<TrajectoryFormat> DetectTrajectoryFormat(
    std::string_view text, const std::string& name) {
  for (const auto& [line_number, line_view] : DataLines(text)) {
    const absl::string_view line(line_view.data(), line_view.size());
    absl::StatusOr<std::vector<double>> numbers =
        LineNumbers(line, absl::StrCat(name, ":", line_number));
    if (!numbers.ok()) return numbers.status();
    if (numbers->size() == 12) return TrajectoryFormat::kKitti;
    if (numbers->size() == 8) return TrajectoryFormat::kTum;
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s:%d: %d fields: neither KITTI (12) nor TUM (8); give --format", name,
        line_number, numbers->size()));
  }
  return absl::NotFoundError(absl::StrCat(name, ": no pose"));
}

absl::StatusOr<Trajectory> ParseTrajectory(std::string_view text,
                                           TrajectoryFormat format,
                                           const std::string& name) {
  const size_t fields = format == TrajectoryFormat::kKitti ? 12 : 8;
  Trajectory trajectory;
  for (const auto& [line_number, line_view] : DataLines(text)) {
    const absl::string_view line(line_view.data(), line_view.size());
    const std::string where = absl::StrCat(name, ":", line_number);
    absl::StatusOr<std::vector<double>> n = LineNumbers(line, where);
    if (!n.ok()) return n.status();
    if (n->size() != fields) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s: %d fields where the %s format has %d", where, n->size(),
          format == TrajectoryFormat::kKitti ? "KITTI" : "TUM", fields));
    }
    StampedPose p;
    if (format == TrajectoryFormat::kKitti) {
      Eigen::Matrix3d r;
      r << (*n)[0], (*n)[1], (*n)[2], (*n)[4], (*n)[5], (*n)[6], (*n)[8],
          (*n)[9], (*n)[10];
      if (!(r.transpose() * r)
               .isApprox(Eigen::Matrix3d::Identity(), kUnitTolerance) ||
          r.determinant() < 0) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": the rotation is not orthonormal"));
      }
      p.time_s = static_cast<double>(trajectory.size());
      p.pose.linear() = r;
      p.pose.translation() << (*n)[3], (*n)[7], (*n)[11];
    } else {
      Eigen::Quaterniond q((*n)[7], (*n)[4], (*n)[5], (*n)[6]);
      if (std::abs(q.norm() - 1.0) > kUnitTolerance) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": the quaternion is not of unit length"));
      }
      if (!trajectory.empty() && (*n)[0] <= trajectory.back().time_s) {
        return absl::InvalidArgumentError(
            absl::StrCat(where, ": timestamps must increase"));
      }
      p.time_s = (*n)[0];
      p.pose.linear() = q.normalized().toRotationMatrix();
      p.pose.translation() << (*n)[1], (*n)[2], (*n)[3];
    }
    trajectory.push_back(p);
  }
  if (trajectory.empty()) {
    return absl::NotFoundError(absl::StrCat(name, ": no pose"));
  }
  return trajectory;
}

absl::StatusOr<Trajectory> ReadTrajectoryFile(
    const std::string& path, std::optional<TrajectoryFormat> format,
    TrajectoryFormat* used) {
  absl::StatusOr<std::string> read = files::ReadFile(path);
  if (!read.ok()) return read.status();
  const std::string& text = *read;
  if (!format) {
    absl::StatusOr<TrajectoryFormat> detected =
        DetectTrajectoryFormat(text, path);
    if (!detected.ok()) return detected.status();
    format = *detected;
  }
  if (used != nullptr) *used = *format;
  return ParseTrajectory(text, *format, path);
}

std::string FormatTrajectory(const Trajectory& trajectory,
                             TrajectoryFormat format) {
  std::string out;
  for (const StampedPose& p : trajectory) {
    const Eigen::Matrix3d r = p.pose.linear();
    const Eigen::Vector3d t = p.pose.translation();
    if (format == TrajectoryFormat::kKitti) {
      absl::StrAppendFormat(&out,
                            "%.9g %.9g %.9g %.9g %.9g %.9g %.9g %.9g "
                            "%.9g %.9g %.9g %.9g\n",
                            r(0, 0), r(0, 1), r(0, 2), t.x(), r(1, 0), r(1, 1),
                            r(1, 2), t.y(), r(2, 0), r(2, 1), r(2, 2), t.z());
    } else {
      const Eigen::Quaterniond q(r);
      absl::StrAppendFormat(&out, "%.6f %.9g %.9g %.9g %.9g %.9g %.9g %.9g\n",
                            p.time_s, t.x(), t.y(), t.z(), q.x(), q.y(), q.z(),
                            q.w());
    }
  }
  return out;
}

Eigen::Isometry3d PlanarPose(double x, double y, double yaw) {
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  pose.linear() =
      Eigen::AngleAxisd(yaw, Eigen::Vector3d::UnitZ()).toRotationMatrix();
  pose.translation() << x, y, 0.0;
  return pose;
}

double YawOf(const Eigen::Isometry3d& pose) {
  return std::atan2(pose.linear()(1, 0), pose.linear()(0, 0));
}

}  // namespace fleetmem::slam
