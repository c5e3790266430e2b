#include "clients/robot/slam/laser_slam.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "opencv2/core.hpp"
#include "opencv2/imgcodecs.hpp"
#include "opencv2/imgproc.hpp"

namespace fleetmem::slam {
namespace {

Pose2 Inverse(const Pose2& p) { return Between(p, Pose2{}); }

}  // namespace

LaserSlam::LaserSlam(std::string robot_id, const LaserSlamOptions& options)
    : robot_id_(std::move(robot_id)),
      options_(options),
      graph_(options.graph) {}

Eigen::Matrix3d LaserSlam::Information(double sigma_m, double sigma_rad) const {
  return Eigen::Vector3d(1 / (sigma_m * sigma_m), 1 / (sigma_m * sigma_m),
                         1 / (sigma_rad * sigma_rad))
      .asDiagonal();
}

Points2 LaserSlam::LocalMap(size_t k, int count_before, int count_after) const {
  Points2 out;
  const Pose2 origin = graph_.pose(keyframes_[k].node);
  const size_t first =
      k >= static_cast<size_t>(count_before) ? k - count_before : 0;
  const size_t last = std::min(keyframes_.size() - 1, k + count_after);
  for (size_t j = first; j <= last; ++j) {
    const Points2 moved = Transform(
        keyframes_[j].points, Between(origin, graph_.pose(keyframes_[j].node)));
    out.insert(out.end(), moved.begin(), moved.end());
  }
  return out;
}

namespace {

bool MovedEnough(const Pose2& keyframe, const Pose2& odometry,
                 const LaserSlamOptions& options) {
  const Pose2 since = Between(keyframe, odometry);
  return std::hypot(since.x, since.y) >= options.keyframe_distance_m ||
         std::abs(since.yaw) >= options.keyframe_turn_rad;
}

}  // namespace

std::vector<size_t> SelectKeyframes(const std::vector<Pose2>& odometry,
                                    const LaserSlamOptions& options) {
  std::vector<size_t> out;
  for (size_t i = 0; i < odometry.size(); ++i) {
    if (out.empty() ||
        MovedEnough(odometry[out.back()], odometry[i], options)) {
      out.push_back(i);
    }
  }
  return out;
}

std::optional<size_t> LaserSlam::AddScan(int64_t timestamp_ns,
                                         const Pose2& odometry,
                                         const robot::LaserScan& scan,
                                         KeyframeChoice choice) {
  ++counters_.scans;
  if (last_odometry_) {
    path_m_ += std::hypot(odometry.x - last_odometry_->x,
                          odometry.y - last_odometry_->y);
  }
  last_odometry_ = odometry;
  const bool keyframe =
      keyframes_.empty() || choice == KeyframeChoice::kKeyframe ||
      (choice == KeyframeChoice::kByMotion &&
       MovedEnough(keyframes_.back().odometry, odometry, options_));
  if (!keyframe) {
    scans_.push_back(ScanRecord{timestamp_ns, keyframes_.size() - 1, odometry});
    return std::nullopt;
  }
  Keyframe kf;
  kf.timestamp_ns = timestamp_ns;
  kf.odometry = odometry;
  kf.path_m = path_m_;
  kf.points = ScanPoints(scan, options_.max_range_m);
  if (keyframes_.empty()) {
    kf.node = graph_.AddNode(Pose2{});
  } else {
    const Keyframe& prev = keyframes_.back();
    const Pose2 odo = Between(prev.odometry, odometry);
    const ScanMatcher matcher(
        LocalMap(keyframes_.size() - 1, options_.local_map_keyframes - 1, 0),
        options_.odometry_match);
    const ScanMatch m = matcher.Match(kf.points, odo);
    // A match far from odometry is a wrong match, not a better odometry.
    const bool plausible = std::hypot(m.pose.x - odo.x, m.pose.y - odo.y) <
                               0.3 + 0.2 * std::hypot(odo.x, odo.y) &&
                           std::abs(NormalizeAngle(m.pose.yaw - odo.yaw)) < 0.2;
    const bool matched = m.accepted && plausible;
    const Pose2 edge = matched ? m.pose : odo;
    kf.node = graph_.AddNode(Compose(graph_.pose(prev.node), edge));
    const absl::Status s = graph_.AddEdge(
        prev.node, kf.node, edge,
        matched
            ? Information(options_.matched_sigma_m, options_.matched_sigma_rad)
            : Information(options_.odometry_sigma_m,
                          options_.odometry_sigma_rad),
        EdgeKind::kOdometry);
    (void)s;  // nodes exist and the information is positive definite
    ++(matched ? counters_.odometry_matched : counters_.odometry_unmatched);
  }
  keyframes_.push_back(std::move(kf));
  keyframe_by_time_[timestamp_ns] = keyframes_.size() - 1;
  scans_.push_back(ScanRecord{timestamp_ns, keyframes_.size() - 1, odometry});
  ++counters_.keyframes;
  return keyframes_.size() - 1;
}

absl::Status LaserSlam::Optimize() {
  ++counters_.optimisations;
  absl::StatusOr<SolveReport> r = graph_.Optimize();
  if (!r.ok()) return r.status();
  counters_.loops_rejected_graph += r->rejected_loops.size();
  counters_.loops_accepted -=
      std::min<uint64_t>(counters_.loops_accepted, r->rejected_loops.size());
  return absl::OkStatus();
}

bool LaserSlam::CloseOwnLoop(size_t keyframe, const LoopCandidate& c,
                             const Eigen::Matrix3d& loop_info) {
  const Keyframe& kf = keyframes_[keyframe];
  auto it = keyframe_by_time_.find(c.timestamp_ns);
  if (it == keyframe_by_time_.end()) return false;
  const size_t other = it->second;
  if (other >= keyframe ||
      kf.path_m - keyframes_[other].path_m < options_.min_loop_path_m) {
    return false;
  }
  ++counters_.loops_proposed;
  const ScanMatcher matcher(LocalMap(other, 2, 2), options_.loop_match);
  const Pose2 guess =
      Between(graph_.pose(keyframes_[other].node), graph_.pose(kf.node));
  const ScanMatch m = matcher.MatchBest(
      kf.points,
      InitialGuesses(guess, options_.own_yaw_span_rad, 0.25,
                     options_.own_xy_span_m, options_.own_xy_span_m));
  if (!m.accepted) {
    ++counters_.loops_rejected_geometry;
    return false;
  }
  if (!graph_
           .AddEdge(keyframes_[other].node, kf.node, m.pose, loop_info,
                    EdgeKind::kLoop)
           .ok()) {
    return false;
  }
  return true;
}

bool LaserSlam::ClosePeerLoop(size_t keyframe, const LoopCandidate& c,
                              const Eigen::Matrix3d& loop_info) {
  const Keyframe& kf = keyframes_[keyframe];
  auto anchor = anchors_.find(c.robot_id);
  std::vector<Pose2> guesses;
  if (anchor != anchors_.end() &&
      anchor_loops_[c.robot_id] >= options_.anchor_loops_for_prior) {
    // The maps are joined: the anchor predicts where this keyframe is
    // in the peer's frame. A candidate far from that is another place
    // that looks alike; a near one is verified around the prediction.
    const Pose2 predicted =
        Compose(Inverse(graph_.pose(anchor->second)), graph_.pose(kf.node));
    if (std::hypot(predicted.x - c.pose.x, predicted.y - c.pose.y) >
        options_.anchored_peer_radius_m) {
      return false;
    }
    guesses =
        InitialGuesses(Between(c.pose, predicted), options_.own_yaw_span_rad,
                       0.25, options_.own_xy_span_m, options_.own_xy_span_m);
  } else {
    // Codes are rotation invariant: search every heading near the
    // peer's keyframe.
    guesses = InitialGuesses(Pose2{}, M_PI, M_PI / 8, 0.5, 0.5);
  }
  ++counters_.loops_proposed;
  const ScanMatcher matcher(ScanPoints(c.scan, options_.max_range_m),
                            options_.loop_match);
  const ScanMatch m = matcher.MatchBest(kf.points, guesses);
  if (!m.accepted) {
    ++counters_.loops_rejected_geometry;
    return false;
  }
  const Pose2 in_peer = Compose(c.pose, m.pose);
  if (anchor == anchors_.end()) {
    const size_t node =
        graph_.AddNode(Compose(graph_.pose(kf.node), Inverse(in_peer)));
    anchor = anchors_.emplace(c.robot_id, node).first;
  }
  if (!graph_
           .AddEdge(anchor->second, kf.node, in_peer, loop_info,
                    EdgeKind::kLoop)
           .ok()) {
    return false;
  }
  ++counters_.inter_robot_loops;
  ++anchor_loops_[c.robot_id];
  return true;
}

absl::StatusOr<int> LaserSlam::CloseLoops(
    size_t keyframe, const std::vector<LoopCandidate>& candidates) {
  if (keyframe >= keyframes_.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("no keyframe ", keyframe, " (", keyframes_.size(), ")"));
  }
  const Eigen::Matrix3d loop_info =
      Information(options_.loop_sigma_m, options_.loop_sigma_rad);
  int accepted = 0;
  for (const LoopCandidate& c : candidates) {
    const bool closed = c.robot_id == robot_id_
                            ? CloseOwnLoop(keyframe, c, loop_info)
                            : ClosePeerLoop(keyframe, c, loop_info);
    if (!closed) continue;
    ++counters_.loops_accepted;
    ++accepted;
  }
  if (accepted > 0) {
    if (absl::Status s = Optimize(); !s.ok()) return s;
  }
  return accepted;
}

Pose2 LaserSlam::KeyframePose(size_t keyframe) const {
  return graph_.pose(keyframes_[keyframe].node);
}

Trajectory LaserSlam::ScanTrajectory() const {
  Trajectory out;
  for (const ScanRecord& s : scans_) {
    const Keyframe& kf = keyframes_[s.keyframe];
    const Pose2 p =
        Compose(graph_.pose(kf.node), Between(kf.odometry, s.odometry));
    out.push_back({s.timestamp_ns * 1e-9, PlanarPose(p.x, p.y, p.yaw)});
  }
  return out;
}

Trajectory LaserSlam::OdometryTrajectory() const {
  Trajectory out;
  for (const ScanRecord& s : scans_) {
    out.push_back({s.timestamp_ns * 1e-9,
                   PlanarPose(s.odometry.x, s.odometry.y, s.odometry.yaw)});
  }
  return out;
}

std::optional<Pose2> LaserSlam::FrameInPeer(const std::string& peer) const {
  auto it = anchors_.find(peer);
  if (it == anchors_.end()) return std::nullopt;
  return Inverse(graph_.pose(it->second));
}

std::vector<std::string> LaserSlam::Peers() const {
  std::vector<std::string> out;
  for (const auto& [peer, node] : anchors_) out.push_back(peer);
  return out;
}

std::vector<std::pair<Pose2, Points2>> LaserSlam::MapScans(
    bool at_odometry) const {
  std::vector<std::pair<Pose2, Points2>> out;
  for (const Keyframe& kf : keyframes_) {
    out.emplace_back(at_odometry ? kf.odometry : graph_.pose(kf.node),
                     kf.points);
  }
  return out;
}

absl::Status WriteOccupancyPng(
    const std::vector<std::pair<Pose2, Points2>>& scans, double resolution_m,
    const std::string& path) {
  double min_x = 1e18, min_y = 1e18, max_x = -1e18, max_y = -1e18;
  for (const auto& [pose, points] : scans) {
    for (const Eigen::Vector2d& w : Transform(points, pose)) {
      min_x = std::min(min_x, w.x());
      min_y = std::min(min_y, w.y());
      max_x = std::max(max_x, w.x());
      max_y = std::max(max_y, w.y());
    }
  }
  if (scans.empty() || min_x > max_x) {
    return absl::InvalidArgumentError("no scan points for the map");
  }
  const int margin = 10;
  const int width =
      static_cast<int>((max_x - min_x) / resolution_m) + 2 * margin;
  const int height =
      static_cast<int>((max_y - min_y) / resolution_m) + 2 * margin;
  if (width > 20000 || height > 20000) {
    return absl::InvalidArgumentError("map larger than 20000 pixels a side");
  }
  // Counts of beams that passed through (free) and ended (hit) per cell.
  cv::Mat free_count = cv::Mat::zeros(height, width, CV_16U);
  cv::Mat hit_count = cv::Mat::zeros(height, width, CV_16U);
  auto pixel = [&](double x, double y) {
    return cv::Point(
        static_cast<int>((x - min_x) / resolution_m) + margin,
        height - 1 - (static_cast<int>((y - min_y) / resolution_m) + margin));
  };
  cv::Mat ray = cv::Mat::zeros(height, width, CV_8U);
  for (const auto& [pose, points] : scans) {
    const cv::Point origin = pixel(pose.x, pose.y);
    ray.setTo(0);
    for (const Eigen::Vector2d& w : Transform(points, pose)) {
      cv::line(ray, origin, pixel(w.x(), w.y()), cv::Scalar(1));
    }
    cv::add(free_count, ray, free_count, cv::noArray(), CV_16U);
    for (const Eigen::Vector2d& w : Transform(points, pose)) {
      const cv::Point p = pixel(w.x(), w.y());
      hit_count.at<uint16_t>(p) += 1;
    }
  }
  cv::Mat image(height, width, CV_8U, cv::Scalar(205));
  for (int r = 0; r < height; ++r) {
    for (int c = 0; c < width; ++c) {
      const int hits = hit_count.at<uint16_t>(r, c);
      const int passes = free_count.at<uint16_t>(r, c);
      if (hits > 0 && hits * 4 >= passes) {
        image.at<uint8_t>(r, c) = 0;
      } else if (passes > 0) {
        image.at<uint8_t>(r, c) = 255;
      }
    }
  }
  if (!cv::imwrite(path, image)) {
    return absl::InternalError(absl::StrCat("cannot write ", path));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::slam
