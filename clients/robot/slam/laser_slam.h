// The laser SLAM back end of a robot (CL-SLAM Sec. 3.3 on 2-D scans, with
// the fleet as the place memory): keyframes by travelled distance or turn,
// odometry edges refined by scan matching against the last keyframes,
// loop candidates from place recognition (the caller asks the fleet's
// QueryPlace and hands them in), a geometric check by scan matching that
// accepts or rejects each candidate, and the Ceres pose graph re-optimised
// on every accepted loop.
//
// Candidates from the robot's own traces become loop edges between two of
// its keyframes. Candidates from a peer are in the peer's map frame: the
// first verified one places an anchor node for that peer (the pose of the
// peer's frame in this robot's frame, Kim et al. 2010's anchor nodes), and
// every inter-robot loop is an edge from that anchor to the keyframe, so
// one optimisation connects both robots' maps.
#ifndef FLEETMEM_CLIENTS_ROBOT_SLAM_LASER_SLAM_H_
#define FLEETMEM_CLIENTS_ROBOT_SLAM_LASER_SLAM_H_

#include <cstdint>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/sensing/observation.h"
#include "clients/robot/slam/pose_graph.h"
#include "clients/robot/slam/scan_matcher.h"
#include "clients/robot/slam/trajectory.h"

namespace fleetmem::slam {

struct LaserSlamOptions {
  // A scan becomes a keyframe after this much odometry travel or turn.
  double keyframe_distance_m = 0.5;
  double keyframe_turn_rad = 0.35;
  // Returns beyond this are ignored by the scan matcher.
  double max_range_m = 25.0;
  // Odometry edges match the scan against this many previous keyframes.
  int local_map_keyframes = 6;
  // Own loop candidates must be at least this much path back.
  double min_loop_path_m = 15.0;
  // A loop to an own keyframe is verified from initial guesses within
  // these spans around the current estimate (yaw, x/y).
  double own_yaw_span_rad = 0.5;
  double own_xy_span_m = 1.0;
  // After this many verified loops with a peer its anchor is trusted as a
  // prior: peers' candidates farther than anchored_peer_radius_m from the
  // predicted place are skipped, nearer ones are verified locally.
  int anchor_loops_for_prior = 3;
  double anchored_peer_radius_m = 8.0;
  // Geometric check of a candidate; stricter than odometry matching.
  ScanMatchOptions loop_match{.max_iterations = 40,
                              .max_correspondence_m = 1.5,
                              .final_correspondence_m = 0.2,
                              .min_inlier_ratio = 0.75,
                              .max_rms_m = 0.06,
                              .min_conditioning = 0.1};
  ScanMatchOptions odometry_match{};
  // Standard deviations of the edges (metres, radians).
  double matched_sigma_m = 0.03;
  double matched_sigma_rad = 0.01;
  double odometry_sigma_m = 0.15;
  double odometry_sigma_rad = 0.05;
  double loop_sigma_m = 0.05;
  double loop_sigma_rad = 0.02;
  PoseGraphOptions graph;
};

// A place-recognition answer, from the fleet's memory.
struct LoopCandidate {
  std::string robot_id;
  int64_t timestamp_ns = 0;
  // The keyframe's pose in its robot's map frame (as it uploaded it).
  Pose2 pose;
  // The keyframe's scan (from the trace's attachment).
  robot::LaserScan scan;
};

struct LaserSlamCounters {
  uint64_t scans = 0;
  uint64_t keyframes = 0;
  uint64_t odometry_matched = 0;
  uint64_t odometry_unmatched = 0;
  uint64_t loops_proposed = 0;
  uint64_t loops_accepted = 0;
  uint64_t loops_rejected_geometry = 0;
  uint64_t loops_rejected_graph = 0;
  uint64_t inter_robot_loops = 0;
  uint64_t optimisations = 0;
};

// Thread-compatible.
class LaserSlam {
 public:
  LaserSlam(std::string robot_id, const LaserSlamOptions& options);

  // Whether a scan becomes a keyframe: by the options' travel and turn, or
  // as the caller decided (a keyframe source that selected them already).
  enum class KeyframeChoice { kByMotion, kKeyframe, kNotKeyframe };
  // One scan with its odometry pose (the robot's own frame). Returns the
  // keyframe index when the scan became a keyframe. The first scan always
  // does.
  std::optional<size_t> AddScan(
      int64_t timestamp_ns, const Pose2& odometry, const robot::LaserScan& scan,
      KeyframeChoice choice = KeyframeChoice::kByMotion);
  // Verifies `candidates` for keyframe `keyframe` (the newest); accepted
  // ones become edges and the graph is re-optimised. Returns how many were
  // accepted. Candidates of the keyframe itself or too recent are skipped.
  absl::StatusOr<int> CloseLoops(size_t keyframe,
                                 const std::vector<LoopCandidate>& candidates);

  size_t num_keyframes() const { return keyframes_.size(); }
  // The current estimate of a keyframe (this robot's map frame).
  Pose2 KeyframePose(size_t keyframe) const;
  int64_t KeyframeTime(size_t keyframe) const {
    return keyframes_[keyframe].timestamp_ns;
  }
  // Path length travelled up to a keyframe (odometry).
  double KeyframePath(size_t keyframe) const {
    return keyframes_[keyframe].path_m;
  }
  // Every scan's pose: its keyframe's estimate composed with the odometry
  // since that keyframe. Times in seconds.
  Trajectory ScanTrajectory() const;
  // The same trajectory as raw odometry.
  Trajectory OdometryTrajectory() const;
  // The pose of this robot's frame in `peer`'s frame, once an inter-robot
  // loop anchored the two maps.
  std::optional<Pose2> FrameInPeer(const std::string& peer) const;
  // Peers anchored so far.
  std::vector<std::string> Peers() const;
  // Keyframe scans (sensor frame) at their estimated poses, for the map,
  // or at their raw odometry poses.
  std::vector<std::pair<Pose2, Points2>> MapScans(
      bool at_odometry = false) const;
  const LaserSlamCounters& counters() const { return counters_; }

 private:
  struct Keyframe {
    size_t node = 0;
    int64_t timestamp_ns = 0;
    Pose2 odometry;
    double path_m = 0.0;
    Points2 points;
  };
  struct ScanRecord {
    int64_t timestamp_ns = 0;
    size_t keyframe = 0;
    Pose2 odometry;
  };
  // CloseLoops' two kinds of candidate: one of this robot's keyframes (far
  // enough back along the path, matched in the local map around it), or a
  // peer's (matched against its scan, the first accepted one anchoring the
  // peer's map in this graph). True if the loop's edge was added.
  bool CloseOwnLoop(size_t keyframe, const LoopCandidate& c,
                    const Eigen::Matrix3d& loop_info);
  bool ClosePeerLoop(size_t keyframe, const LoopCandidate& c,
                     const Eigen::Matrix3d& loop_info);
  Eigen::Matrix3d Information(double sigma_m, double sigma_rad) const;
  // The last keyframes' points in keyframe `k`'s frame.
  Points2 LocalMap(size_t k, int count_before, int count_after) const;
  absl::Status Optimize();

  std::string robot_id_;
  LaserSlamOptions options_;
  PoseGraph2d graph_;
  std::vector<Keyframe> keyframes_;
  std::vector<ScanRecord> scans_;
  std::map<int64_t, size_t> keyframe_by_time_;
  // Peer robot -> anchor node (the peer's frame in this robot's frame).
  std::map<std::string, size_t> anchors_;
  // Verified inter-robot loops per peer.
  std::map<std::string, int> anchor_loops_;
  double path_m_ = 0.0;
  std::optional<Pose2> last_odometry_;
  LaserSlamCounters counters_;
};

// Indices of the keyframes among consecutive odometry poses: the first, then
// each pose that moved keyframe_distance_m or turned keyframe_turn_rad from
// the last keyframe (LaserSlam's rule).
std::vector<size_t> SelectKeyframes(const std::vector<Pose2>& odometry,
                                    const LaserSlamOptions& options);

// A simple occupancy grid of the keyframe scans (free space along each
// beam, occupied at its end), as an 8-bit PNG: white free, black
// occupied, grey unknown. `resolution_m` per pixel.
absl::Status WriteOccupancyPng(
    const std::vector<std::pair<Pose2, Points2>>& scans, double resolution_m,
    const std::string& path);

}  // namespace fleetmem::slam

#endif  // FLEETMEM_CLIENTS_ROBOT_SLAM_LASER_SLAM_H_
