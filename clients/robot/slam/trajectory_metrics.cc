#include "clients/robot/slam/trajectory_metrics.h"

#include <algorithm>
#include <cmath>
#include <map>
#include <numeric>

#include "Eigen/Geometry"
#include "Eigen/SVD"
#include "absl/container/flat_hash_map.h"
#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"

namespace fleetmem::slam {
namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kDegPerRad = 180.0 / kPi;

// Angle of a rotation matrix in radians, in [0, pi]; the cosine is clamped
// as the KITTI devkit clamps it.
double RotationAngle(const Eigen::Matrix3d& r) {
  const double c = std::clamp(0.5 * (r.trace() - 1.0), -1.0, 1.0);
  return std::acos(c);
}

// Cumulative path length of the positions, from 0.
std::vector<double> PathLengths(const Trajectory& poses) {
  std::vector<double> lengths(poses.size(), 0.0);
  for (size_t i = 1; i < poses.size(); ++i) {
    lengths[i] =
        lengths[i - 1] +
        (poses[i].pose.translation() - poses[i - 1].pose.translation()).norm();
  }
  return lengths;
}

double WrapAngle(double a) { return std::remainder(a, 2.0 * kPi); }

}  // namespace

ErrorStats Summarize(std::vector<double> errors) {
  ErrorStats s;
  s.count = errors.size();
  if (errors.empty()) return s;
  const double n = static_cast<double>(errors.size());
  double sum = 0.0, sum_sq = 0.0;
  for (double e : errors) {
    sum += e;
    sum_sq += e * e;
  }
  s.mean = sum / n;
  s.rmse = std::sqrt(sum_sq / n);
  double var = 0.0;
  for (double e : errors) var += (e - s.mean) * (e - s.mean);
  s.std = std::sqrt(var / n);
  std::sort(errors.begin(), errors.end());
  s.min = errors.front();
  s.max = errors.back();
  const size_t mid = errors.size() / 2;
  s.median = errors.size() % 2 == 1 ? errors[mid]
                                    : 0.5 * (errors[mid - 1] + errors[mid]);
  return s;
}

absl::StatusOr<Similarity> Umeyama(const Eigen::Matrix3Xd& source,
                                   const Eigen::Matrix3Xd& target,
                                   bool with_scale) {
  if (source.cols() != target.cols()) {
    return absl::InvalidArgumentError(
        absl::StrFormat("Umeyama: %d source points but %d target points",
                        source.cols(), target.cols()));
  }
  if (source.cols() < 3) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "Umeyama: %d points; at least 3 are needed", source.cols()));
  }
  const Eigen::Vector3d mean = source.rowwise().mean();
  if ((source.colwise() - mean).squaredNorm() == 0.0) {
    return absl::InvalidArgumentError(
        "Umeyama: every source point is the same; no alignment exists");
  }
  const Eigen::Matrix4d t = Eigen::umeyama(source, target, with_scale);
  Similarity s;
  s.scale = with_scale ? std::cbrt(t.topLeftCorner<3, 3>().determinant()) : 1.0;
  s.rotation = t.topLeftCorner<3, 3>() / s.scale;
  s.translation = t.topRightCorner<3, 1>();
  return s;
}

Association AssociateByTime(const Trajectory& reference,
                            const Trajectory& estimate, double max_diff_s) {
  const bool estimate_longer = estimate.size() > reference.size();
  const Trajectory& shorter = estimate_longer ? reference : estimate;
  const Trajectory& longer = estimate_longer ? estimate : reference;
  std::vector<double> times(longer.size());
  for (size_t i = 0; i < longer.size(); ++i) times[i] = longer[i].time_s;
  Association a;
  for (size_t i = 0; i < shorter.size(); ++i) {
    const double t = shorter[i].time_s;
    // Nearest time in the longer trajectory (its times increase); the first
    // of equally near ones, as numpy's argmin picks.
    auto it = std::lower_bound(times.begin(), times.end(), t);
    size_t best = it == times.end() ? times.size() - 1 : it - times.begin();
    if (best > 0 &&
        std::abs(times[best - 1] - t) <= std::abs(times[best] - t)) {
      --best;
    }
    if (std::abs(times[best] - t) > max_diff_s) continue;
    a.reference.push_back(estimate_longer ? i : best);
    a.estimate.push_back(estimate_longer ? best : i);
  }
  return a;
}

absl::StatusOr<std::pair<Trajectory, Trajectory>> AssociatedPoses(
    const Trajectory& reference, const Trajectory& estimate, bool by_index,
    double max_diff_s) {
  std::pair<Trajectory, Trajectory> out;
  if (by_index) {
    if (reference.size() != estimate.size()) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "the reference has %d poses and the estimate %d; without "
          "timestamps (KITTI) they must have the same number",
          reference.size(), estimate.size()));
    }
    out = {reference, estimate};
  } else {
    const Association a = AssociateByTime(reference, estimate, max_diff_s);
    for (size_t k = 0; k < a.reference.size(); ++k) {
      out.first.push_back(reference[a.reference[k]]);
      out.second.push_back(estimate[a.estimate[k]]);
    }
  }
  if (out.first.size() < 3) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%d poses associate (max time difference %g s); at least 3 are needed",
        out.first.size(), max_diff_s));
  }
  return out;
}

absl::StatusOr<Alignment> ParseAlignment(std::string_view name) {
  if (name == "none") return Alignment::kNone;
  if (name == "se3") return Alignment::kSe3;
  if (name == "sim3") return Alignment::kSim3;
  return absl::InvalidArgumentError(absl::StrCat(
      "unknown alignment '", std::string(name), "' (none, se3, sim3)"));
}

absl::StatusOr<AteResult> AbsoluteTrajectoryError(const Trajectory& reference,
                                                  const Trajectory& estimate,
                                                  Alignment alignment) {
  if (reference.size() != estimate.size()) {
    return absl::InvalidArgumentError("ATE needs associated poses");
  }
  const size_t n = reference.size();
  Eigen::Matrix3Xd ref(3, n), est(3, n);
  for (size_t i = 0; i < n; ++i) {
    ref.col(i) = reference[i].pose.translation();
    est.col(i) = estimate[i].pose.translation();
  }
  AteResult result;
  if (alignment != Alignment::kNone) {
    absl::StatusOr<Similarity> s =
        Umeyama(est, ref, alignment == Alignment::kSim3);
    if (!s.ok()) return s.status();
    result.alignment = *s;
  }
  std::vector<double> errors(n);
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d aligned =
        result.alignment.scale * result.alignment.rotation * est.col(i) +
        result.alignment.translation;
    errors[i] = (aligned - ref.col(i)).norm();
  }
  result.translation_m = Summarize(std::move(errors));
  return result;
}

absl::StatusOr<RpeResult> RelativePoseError(const Trajectory& reference,
                                            const Trajectory& estimate,
                                            const RpeOptions& options) {
  if (reference.size() != estimate.size()) {
    return absl::InvalidArgumentError("RPE needs associated poses");
  }
  RpeResult result;
  const Trajectory& basis = options.pairs_from_reference ? reference : estimate;
  std::vector<size_t> ids;
  if (options.delta_m > 0.0) {
    // Each id is the first pose whose path since the previous id reaches
    // delta_m (the path counted from the first pose for the first id).
    double path = 0.0;
    for (size_t i = 1; i < basis.size(); ++i) {
      path += (basis[i].pose.translation() - basis[i - 1].pose.translation())
                  .norm();
      if (path >= options.delta_m) {
        ids.push_back(i);
        path = 0.0;
      }
    }
  } else {
    if (options.delta_frames < 1) {
      return absl::InvalidArgumentError("the RPE frame delta must be >= 1");
    }
    for (size_t i = 0; i < basis.size(); i += options.delta_frames) {
      ids.push_back(i);
    }
  }
  for (size_t k = 0; k + 1 < ids.size(); ++k) {
    result.pairs.emplace_back(ids[k], ids[k + 1]);
  }
  if (result.pairs.empty()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "RPE: delta %s gives no pose pair on a trajectory of %d poses",
        options.delta_m > 0 ? absl::StrCat(options.delta_m, " m")
                            : absl::StrCat(options.delta_frames, " frames"),
        basis.size()));
  }
  std::vector<double> trans, rot;
  for (const auto& [i, j] : result.pairs) {
    const Eigen::Isometry3d q = reference[i].pose.inverse() * reference[j].pose;
    const Eigen::Isometry3d p = estimate[i].pose.inverse() * estimate[j].pose;
    const Eigen::Isometry3d e = q.inverse() * p;
    trans.push_back(e.translation().norm());
    rot.push_back(std::abs(Eigen::AngleAxisd(e.linear()).angle()) * kDegPerRad);
  }
  result.translation_m = Summarize(std::move(trans));
  result.rotation_deg = Summarize(std::move(rot));
  return result;
}

KittiOdometryResult KittiOdometryError(const Trajectory& reference,
                                       const Trajectory& estimate,
                                       const KittiSegments& segments) {
  const size_t kStep = static_cast<size_t>(std::max(1, segments.step_frames));
  const std::vector<double>& kLengths = segments.lengths_m;
  const std::vector<double> dist = PathLengths(reference);
  KittiOdometryResult result;
  double t_sum = 0.0, r_sum = 0.0;
  const size_t n = std::min(reference.size(), estimate.size());
  for (size_t first = 0; first < n; first += kStep) {
    for (double len : kLengths) {
      // The first frame more than `len` metres of path after `first`.
      size_t last = first;
      while (last < n && dist[last] <= dist[first] + len) ++last;
      if (last >= n) continue;
      // General 4x4 inverses, as the devkit takes them: the files' rotations
      // are orthonormal only to their printed digits.
      const Eigen::Matrix4d gt = reference[first].pose.matrix().inverse() *
                                 reference[last].pose.matrix();
      const Eigen::Matrix4d est = estimate[first].pose.matrix().inverse() *
                                  estimate[last].pose.matrix();
      const Eigen::Matrix4d error = est.inverse() * gt;
      t_sum += error.topRightCorner<3, 1>().norm() / len;
      r_sum += RotationAngle(error.topLeftCorner<3, 3>()) / len;
      ++result.segments;
    }
  }
  if (result.segments > 0) {
    result.t_err_percent = 100.0 * t_sum / result.segments;
    result.r_err_deg_per_100m = 100.0 * kDegPerRad * r_sum / result.segments;
  }
  return result;
}

absl::StatusOr<std::vector<Relation>> ParseRelations(std::string_view text,
                                                     const std::string& name) {
  std::vector<Relation> relations;
  for (const auto& [line_number, line_view] : DataLines(text)) {
    const absl::string_view line(line_view.data(), line_view.size());
    std::vector<absl::string_view> fields =
        absl::StrSplit(line, absl::ByAnyChar(" \t"), absl::SkipEmpty());
    double v[8];
    bool ok = fields.size() == 8;
    for (size_t i = 0; ok && i < 8; ++i) {
      ok = absl::SimpleAtod(fields[i], &v[i]) && std::isfinite(v[i]);
    }
    if (!ok) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "%s:%d: a relation is `t1 t2 x y z roll pitch yaw` (8 numbers)", name,
          line_number));
    }
    relations.push_back(Relation{v[0], v[1], v[2], v[3], v[7]});
  }
  if (relations.empty()) {
    return absl::NotFoundError(absl::StrCat(name, ": no relation"));
  }
  return relations;
}

absl::StatusOr<RelationsResult> RelationsError(
    const Trajectory& estimate, const std::vector<Relation>& relations,
    double max_diff_s) {
  RelationsResult result;
  if (estimate.empty()) return absl::InvalidArgumentError("empty estimate");
  std::vector<double> times(estimate.size());
  for (size_t i = 0; i < estimate.size(); ++i) times[i] = estimate[i].time_s;
  auto nearest = [&](double t) -> const StampedPose* {
    auto it = std::lower_bound(times.begin(), times.end(), t);
    size_t k = it == times.end() ? times.size() - 1 : it - times.begin();
    if (k > 0 && std::abs(times[k - 1] - t) <= std::abs(times[k] - t)) --k;
    return std::abs(times[k] - t) <= max_diff_s ? &estimate[k] : nullptr;
  };
  std::vector<double> trans, rot, trans_sq, rot_sq;
  for (const Relation& r : relations) {
    const StampedPose* a = nearest(r.t1);
    const StampedPose* b = nearest(r.t2);
    if (a == nullptr || b == nullptr) {
      ++result.missing;
      continue;
    }
    // Planar relative pose of the estimate, then its difference from the
    // relation: delta_ref^-1 * delta_est.
    const Eigen::Vector3d d = b->pose.translation() - a->pose.translation();
    const double ya = YawOf(a->pose);
    const double c = std::cos(ya), s = std::sin(ya);
    const Eigen::Vector2d est_t(c * d.x() + s * d.y(), -s * d.x() + c * d.y());
    const double est_yaw = WrapAngle(YawOf(b->pose) - ya);
    const Eigen::Vector2d diff = est_t - Eigen::Vector2d(r.x, r.y);
    const double cr = std::cos(r.yaw), sr = std::sin(r.yaw);
    const Eigen::Vector2d err_t(cr * diff.x() + sr * diff.y(),
                                -sr * diff.x() + cr * diff.y());
    const double err_yaw = std::abs(WrapAngle(est_yaw - r.yaw)) * kDegPerRad;
    trans.push_back(err_t.norm());
    rot.push_back(err_yaw);
    trans_sq.push_back(err_t.squaredNorm());
    rot_sq.push_back(err_yaw * err_yaw);
  }
  if (trans.empty()) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "none of the %d relations has both scan times in the estimate "
        "(within %g s)",
        relations.size(), max_diff_s));
  }
  const ErrorStats tsq = Summarize(trans_sq), rsq = Summarize(rot_sq);
  result.translation_sq_mean = tsq.mean;
  result.translation_sq_std = tsq.std;
  result.rotation_sq_mean = rsq.mean;
  result.rotation_sq_std = rsq.std;
  result.translation_m = Summarize(std::move(trans));
  result.rotation_deg = Summarize(std::move(rot));
  return result;
}

absl::StatusOr<std::vector<Deployment>> ParseDeployments(
    std::string_view text, const std::string& name) {
  std::vector<Deployment> out;
  int col_seq = -1, col_t = -1, col_r = -1;
  for (const auto& [line_number, line_view] : DataLines(text)) {
    const absl::string_view line(line_view.data(), line_view.size());
    std::vector<std::string> fields = absl::StrSplit(line, ',');
    for (std::string& f : fields) absl::StripAsciiWhitespace(&f);
    if (col_seq < 0) {
      for (size_t i = 0; i < fields.size(); ++i) {
        if (fields[i] == "sequence") col_seq = i;
        if (fields[i] == "t_err") col_t = i;
        if (fields[i] == "r_err") col_r = i;
      }
      if (col_seq < 0 || col_t < 0 || col_r < 0) {
        return absl::InvalidArgumentError(absl::StrCat(
            name, ":", line_number,
            ": the header must name the columns sequence, t_err, r_err"));
      }
      continue;
    }
    const size_t need = std::max({col_seq, col_t, col_r}) + 1;
    Deployment d;
    bool ok = fields.size() >= need &&
              absl::SimpleAtod(fields[col_t], &d.t_err_percent) &&
              absl::SimpleAtod(fields[col_r], &d.r_err_deg_per_100m) &&
              std::isfinite(d.t_err_percent) && d.t_err_percent >= 0 &&
              std::isfinite(d.r_err_deg_per_100m) && d.r_err_deg_per_100m >= 0;
    if (ok) {
      for (absl::string_view s : absl::StrSplit(fields[col_seq], '>')) {
        s = absl::StripAsciiWhitespace(s);
        ok = ok && !s.empty();
        d.scenes.emplace_back(s);
      }
      ok = ok && d.scenes.size() >= 2;
    }
    if (!ok) {
      return absl::InvalidArgumentError(absl::StrCat(
          name, ":", line_number,
          ": a deployment is `scene>scene[>...],t_err,r_err` with at least "
          "two scenes and errors >= 0"));
    }
    out.push_back(std::move(d));
  }
  if (out.empty()) {
    return absl::NotFoundError(absl::StrCat(name, ": no deployment"));
  }
  return out;
}

absl::StatusOr<ContinualScores> ScoreDeployments(
    const std::vector<Deployment>& deployments) {
  auto environment = [](const std::string& scene) {
    size_t end = scene.size();
    while (end > 1 && absl::ascii_isdigit(scene[end - 1])) --end;
    return scene.substr(0, end);
  };
  auto trans = [](const Deployment& d) {
    return std::max(0.0, 1.0 - d.t_err_percent / 100.0);
  };
  auto rot = [](const Deployment& d) {
    return 1.0 - d.r_err_deg_per_100m / 180.0;
  };
  absl::flat_hash_map<std::string, const Deployment*> by_sequence;
  for (const Deployment& d : deployments) {
    const std::string key = absl::StrJoin(d.scenes, ">");
    if (!by_sequence.emplace(key, &d).second) {
      return absl::InvalidArgumentError(
          absl::StrCat("deployment '", key, "' appears twice"));
    }
  }
  ContinualScores scores;
  for (const Deployment& d : deployments) {
    const std::string last = environment(d.scenes.back());
    // Scenes after the initialisation, before the last one.
    const size_t n = d.scenes.size();
    bool seen = false;
    for (size_t i = 1; i + 1 < n; ++i) {
      seen = seen || environment(d.scenes[i]) == last;
    }
    if (!seen) {
      scores.aq_trans += trans(d);
      scores.aq_rot += rot(d);
      ++scores.aq_sequences;
      continue;
    }
    // Revisit: the run of other environments right before the last scene.
    size_t run_start = n - 1;
    while (run_start > 1 && environment(d.scenes[run_start - 1]) != last) {
      --run_start;
    }
    if (run_start == n - 1) continue;  // no intermediate deployment
    std::vector<std::string> without(d.scenes.begin(),
                                     d.scenes.begin() + run_start);
    without.push_back(d.scenes.back());
    const std::string key = absl::StrJoin(without, ">");
    auto it = by_sequence.find(key);
    if (it == by_sequence.end()) {
      return absl::InvalidArgumentError(
          absl::StrCat("RQ: '", absl::StrJoin(d.scenes, ">"), "' needs '", key,
                       "' (the same without the intermediate "
                       "deployment), which the table lacks"));
    }
    scores.rq_trans += trans(d) - trans(*it->second);
    scores.rq_rot += rot(d) - rot(*it->second);
    ++scores.rq_pairs;
  }
  if (scores.aq_sequences > 0) {
    scores.aq_trans /= scores.aq_sequences;
    scores.aq_rot /= scores.aq_sequences;
  }
  if (scores.rq_pairs > 0) {
    scores.rq_trans /= scores.rq_pairs;
    scores.rq_rot /= scores.rq_pairs;
  }
  return scores;
}

}  // namespace fleetmem::slam
