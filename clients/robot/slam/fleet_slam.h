// Laser SLAM on a fleetmem robot, with the fleet's memory as its place
// memory (docs/slam.md):
//
//   KeyframeSource  the keyframes of a laser source (a CARMEN log), chosen by
//                   odometry travel and turn: what the agent observes, encodes
//                   and uploads through its durable queue.
//   FleetSlam       the agent's ObservationHook: for each keyframe it feeds
//                   the scans since the last one to LaserSlam (odometry
//                   rebased to the session's first scan: a robot starts in
//                   its own frame), asks the fleet for loop candidates
//                   (QueryPlace: its own traces near its estimate, and
//                   peers' traces by code alone), verifies them, and puts its
//                   pose estimate and the keyframe's scan into the trace.
//
// The trace's pose is the estimate when the keyframe is uploaded; later
// corrections stay on the robot (traces are immutable in the fleet).
#ifndef FLEETMEM_CLIENTS_ROBOT_SLAM_FLEET_SLAM_H_
#define FLEETMEM_CLIENTS_ROBOT_SLAM_FLEET_SLAM_H_

#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/sensing/encoder.h"
#include "clients/robot/sensing/observation_hook.h"
#include "clients/robot/sensing/observation_source.h"
#include "clients/robot/slam/laser_slam.h"

namespace fleetmem::slam {

// Thread-compatible: Read is const and may run concurrently.
class KeyframeSource : public robot::ObservationSource {
 public:
  // Reads every observation of `inner` (scans with odometry places) once
  // to choose the keyframes. INVALID_ARGUMENT if `inner` holds no scans.
  static absl::StatusOr<std::unique_ptr<KeyframeSource>> Open(
      std::unique_ptr<robot::ObservationSource> inner,
      const LaserSlamOptions& options);

  const std::string& description() const override { return description_; }
  size_t size() const override { return keyframes_.size(); }
  // Keyframe `index`, with index = `index` (its position here).
  absl::StatusOr<robot::Observation> Read(size_t index) const override;
  std::string default_domain() const override {
    return inner_->default_domain();
  }
  std::string default_encoder() const override {
    return inner_->default_encoder();
  }
  double default_match_radius() const override {
    return inner_->default_match_radius();
  }
  bool places_are_ground_truth() const override {
    return inner_->places_are_ground_truth();
  }

  const robot::ObservationSource& inner() const { return *inner_; }
  // Index in `inner` of keyframe `index`.
  size_t inner_index(size_t index) const { return keyframes_[index]; }

 private:
  KeyframeSource(std::unique_ptr<robot::ObservationSource> inner,
                 std::vector<size_t> keyframes);

  std::unique_ptr<robot::ObservationSource> inner_;
  std::vector<size_t> keyframes_;
  std::string description_;
};

struct FleetSlamOptions {
  std::string fleet_id;
  std::string robot_id;
  LaserSlamOptions slam;
  // Own candidates: the nearest codes among traces within prior_radius_m
  // of the current estimate; at most own_candidates of this robot's.
  uint32_t own_query_k = 6;
  int own_candidates = 3;
  double prior_radius_m = 8.0;
  // Peers' candidates: the nearest codes of the whole fleet (no prior: a
  // peer's poses are in its own frame); at most peer_candidates of peers'.
  uint32_t peer_query_k = 20;
  int peer_candidates = 2;
};

struct FleetSlamStats {
  uint64_t queries = 0;
  uint64_t queries_failed = 0;
  uint64_t peer_candidates_without_scan = 0;
  double slam_ms = 0.0;   // scan matching, verification, optimisation
  double query_ms = 0.0;  // QueryPlace round trips
};

// Not thread-safe: the agent calls it from its loop.
class FleetSlam : public robot::ObservationHook {
 public:
  // `first_keyframe` is the agent's first index (--first): the session
  // starts there, in its own frame.
  FleetSlam(FleetSlamOptions options, const KeyframeSource* source,
            const robot::Encoder* encoder, client::Client* query_client,
            size_t first_keyframe);

  absl::Status BeforeRecord(size_t index, const robot::Observation& observation,
                            std::span<const float> code,
                            v1::MemoryTrace& trace) override;

  // At the end of the session (keyframes up to `end_keyframe`, exclusive):
  // feeds the scans after the last keyframe, up to the next keyframe or the
  // end of the log, so that the trajectory covers the whole session.
  absl::Status FinishSession(size_t end_keyframe);

  // Writes to `dir`: trajectory.tum (every scan of the session, this
  // robot's frame), odometry.tum, map.png (occupancy, 0.1 m), for each
  // anchored peer trajectory_in_<peer>.tum (the same scans in that peer's
  // frame), and slam.json (counters, anchors, timings).
  absl::Status WriteOutputs(const std::string& dir) const;

  const LaserSlam& slam() const { return slam_; }
  const FleetSlamStats& stats() const { return stats_; }

 private:
  absl::Status Process(size_t index, const robot::Observation& keyframe,
                       std::span<const float> code);
  std::vector<v1::PlaceMatch> Query(std::span<const float> code,
                                    const Pose2* near);

  FleetSlamOptions options_;
  const KeyframeSource* source_;
  const robot::Encoder* encoder_;
  client::Client* query_client_;
  LaserSlam slam_;
  size_t next_keyframe_;
  // Next scan of the inner source to feed; its first scan's odometry.
  size_t next_scan_ = 0;
  bool have_origin_ = false;
  Pose2 origin_;
  FleetSlamStats stats_;
};

}  // namespace fleetmem::slam

#endif  // FLEETMEM_CLIENTS_ROBOT_SLAM_FLEET_SLAM_H_
