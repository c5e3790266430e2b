#include "clients/robot/slam/fleet_slam.h"

#include <chrono>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "services/common/files.h"
#include "clients/robot/slam/trajectory.h"
#include "google/protobuf/struct.pb.h"
#include "google/protobuf/util/json_util.h"

namespace fleetmem::slam {
namespace {

using Clock = std::chrono::steady_clock;

double MsSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start)
      .count();
}

Pose2 OdometryOf(const robot::Observation& o) {
  return Pose2{o.place.x, o.place.y, o.place.yaw};
}

}  // namespace

KeyframeSource::KeyframeSource(std::unique_ptr<robot::ObservationSource> inner,
                               std::vector<size_t> keyframes)
    : inner_(std::move(inner)),
      keyframes_(std::move(keyframes)),
      description_(absl::StrCat("keyframes of ", inner_->description())) {}

absl::StatusOr<std::unique_ptr<KeyframeSource>> KeyframeSource::Open(
    std::unique_ptr<robot::ObservationSource> inner,
    const LaserSlamOptions& options) {
  std::vector<Pose2> odometry;
  odometry.reserve(inner->size());
  for (size_t i = 0; i < inner->size(); ++i) {
    absl::StatusOr<robot::Observation> o = inner->Read(i);
    if (!o.ok()) return o.status();
    if (o->scan.ranges.empty()) {
      return absl::InvalidArgumentError(absl::StrCat(
          inner->description(), ": ", o->name,
          " is not a laser scan; SLAM needs a laser source (carmen:FILE)"));
    }
    odometry.push_back(OdometryOf(*o));
  }
  if (odometry.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(inner->description(), " holds no scan"));
  }
  std::vector<size_t> keyframes = SelectKeyframes(odometry, options);
  return std::unique_ptr<KeyframeSource>(
      new KeyframeSource(std::move(inner), std::move(keyframes)));
}

absl::StatusOr<robot::Observation> KeyframeSource::Read(size_t index) const {
  if (index >= keyframes_.size()) {
    return absl::OutOfRangeError(absl::StrCat(
        description_, ": keyframe ", index, " of ", keyframes_.size()));
  }
  absl::StatusOr<robot::Observation> o = inner_->Read(keyframes_[index]);
  if (o.ok()) o->index = index;
  return o;
}

FleetSlam::FleetSlam(FleetSlamOptions options, const KeyframeSource* source,
                     const robot::Encoder* encoder,
                     client::Client* query_client, size_t first_keyframe)
    : options_(std::move(options)),
      source_(source),
      encoder_(encoder),
      query_client_(query_client),
      slam_(options_.robot_id, options_.slam),
      next_keyframe_(first_keyframe) {}

absl::Status FleetSlam::BeforeRecord(size_t index,
                                     const robot::Observation& observation,
                                     std::span<const float> code,
                                     v1::MemoryTrace& trace) {
  if (index < next_keyframe_) {
    return absl::FailedPreconditionError(absl::StrCat(
        "SLAM: keyframe ", index, " observed again after ", next_keyframe_));
  }
  // A restarted robot resumes past keyframes whose SLAM state was not kept:
  // rebuild it (scan matching and fleet queries again) before going on.
  while (next_keyframe_ < index) {
    absl::StatusOr<robot::Observation> earlier = source_->Read(next_keyframe_);
    if (!earlier.ok()) return earlier.status();
    absl::StatusOr<std::vector<float>> earlier_code =
        encoder_->Encode(*earlier);
    if (!earlier_code.ok()) return earlier_code.status();
    if (absl::Status s = Process(next_keyframe_, *earlier, *earlier_code);
        !s.ok()) {
      return s;
    }
  }
  if (absl::Status s = Process(index, observation, code); !s.ok()) return s;
  const Pose2 estimate = slam_.KeyframePose(slam_.num_keyframes() - 1);
  trace.mutable_pose()->set_x(estimate.x);
  trace.mutable_pose()->set_y(estimate.y);
  trace.mutable_pose()->set_z(0.0);
  trace.mutable_pose()->set_yaw(estimate.yaw);
  trace.set_attachment(EncodeScan(observation.scan));
  return absl::OkStatus();
}

std::vector<v1::PlaceMatch> FleetSlam::Query(std::span<const float> code,
                                             const Pose2* near) {
  v1::QueryPlaceRequest request;
  request.set_fleet_id(options_.fleet_id);
  request.mutable_code()->Assign(code.begin(), code.end());
  request.set_k(near ? options_.own_query_k : options_.peer_query_k);
  if (near != nullptr) {
    request.mutable_near()->set_x(near->x);
    request.mutable_near()->set_y(near->y);
    request.set_radius_m(options_.prior_radius_m);
  }
  ++stats_.queries;
  const Clock::time_point start = Clock::now();
  absl::StatusOr<std::vector<v1::PlaceMatch>> matches =
      query_client_->QueryPlace(request);
  stats_.query_ms += MsSince(start);
  if (!matches.ok()) {
    // An empty fleet answers NOT_FOUND; an unreachable server leaves this
    // keyframe without candidates (the map goes on from odometry).
    if (matches.status().code() != absl::StatusCode::kNotFound) {
      ++stats_.queries_failed;
    }
    return {};
  }
  return *std::move(matches);
}

absl::Status FleetSlam::Process(size_t index,
                                const robot::Observation& keyframe,
                                std::span<const float> code) {
  const size_t target = source_->inner_index(index);
  if (!have_origin_) {
    // The session starts at its first keyframe, in its own frame.
    next_scan_ = target;
    origin_ = OdometryOf(keyframe);
    have_origin_ = true;
  }
  Clock::time_point start = Clock::now();
  std::optional<size_t> k;
  for (; next_scan_ <= target; ++next_scan_) {
    absl::StatusOr<robot::Observation> scan =
        next_scan_ == target ? absl::StatusOr<robot::Observation>(keyframe)
                             : source_->inner().Read(next_scan_);
    if (!scan.ok()) return scan.status();
    k = slam_.AddScan(
        scan->timestamp_ns, Between(origin_, OdometryOf(*scan)), scan->scan,
        next_scan_ == target ? LaserSlam::KeyframeChoice::kKeyframe
                             : LaserSlam::KeyframeChoice::kNotKeyframe);
  }
  stats_.slam_ms += MsSince(start);
  next_keyframe_ = index + 1;
  if (!k) return absl::InternalError("SLAM: the keyframe was not added");

  std::vector<LoopCandidate> candidates;
  const Pose2 here = slam_.KeyframePose(*k);
  int own = 0;
  for (const v1::PlaceMatch& m : Query(code, &here)) {
    if (m.trace().robot_id() != options_.robot_id) continue;
    if (own++ >= options_.own_candidates) break;
    candidates.push_back(
        LoopCandidate{m.trace().robot_id(), m.trace().timestamp_ns(), {}, {}});
  }
  int peer = 0;
  for (const v1::PlaceMatch& m : Query(code, nullptr)) {
    if (m.trace().robot_id() == options_.robot_id) continue;
    if (peer >= options_.peer_candidates) break;
    absl::StatusOr<robot::LaserScan> scan = DecodeScan(m.trace().attachment());
    if (!scan.ok()) {
      ++stats_.peer_candidates_without_scan;
      continue;
    }
    ++peer;
    candidates.push_back(
        LoopCandidate{m.trace().robot_id(), m.trace().timestamp_ns(),
                      Pose2{m.trace().pose().x(), m.trace().pose().y(),
                            m.trace().pose().yaw()},
                      *std::move(scan)});
  }
  start = Clock::now();
  absl::StatusOr<int> closed = slam_.CloseLoops(*k, candidates);
  stats_.slam_ms += MsSince(start);
  return closed.status();
}

absl::Status FleetSlam::FinishSession(size_t end_keyframe) {
  if (!have_origin_) return absl::OkStatus();
  const size_t end = end_keyframe >= source_->size()
                         ? source_->inner().size()
                         : source_->inner_index(end_keyframe);
  for (; next_scan_ < end; ++next_scan_) {
    absl::StatusOr<robot::Observation> scan = source_->inner().Read(next_scan_);
    if (!scan.ok()) return scan.status();
    slam_.AddScan(scan->timestamp_ns, Between(origin_, OdometryOf(*scan)),
                  scan->scan, LaserSlam::KeyframeChoice::kNotKeyframe);
  }
  return absl::OkStatus();
}

absl::Status FleetSlam::WriteOutputs(const std::string& dir) const {
  if (slam_.num_keyframes() == 0) return absl::OkStatus();
  const Trajectory trajectory = slam_.ScanTrajectory();
  if (absl::Status s = files::WriteFile(
          dir + "/trajectory.tum",
          FormatTrajectory(trajectory, TrajectoryFormat::kTum));
      !s.ok()) {
    return s;
  }
  if (absl::Status s = files::WriteFile(
          dir + "/odometry.tum",
          FormatTrajectory(slam_.OdometryTrajectory(), TrajectoryFormat::kTum));
      !s.ok()) {
    return s;
  }
  if (absl::Status s =
          WriteOccupancyPng(slam_.MapScans(), 0.1, dir + "/map.png");
      !s.ok()) {
    return s;
  }
  google::protobuf::Struct report;
  auto& fields = *report.mutable_fields();
  const LaserSlamCounters& c = slam_.counters();
  const std::pair<const char*, double> numbers[] = {
      {"scans", double(c.scans)},
      {"keyframes", double(c.keyframes)},
      {"odometry_matched", double(c.odometry_matched)},
      {"odometry_unmatched", double(c.odometry_unmatched)},
      {"loops_proposed", double(c.loops_proposed)},
      {"loops_accepted", double(c.loops_accepted)},
      {"loops_rejected_geometry", double(c.loops_rejected_geometry)},
      {"loops_rejected_graph", double(c.loops_rejected_graph)},
      {"inter_robot_loops", double(c.inter_robot_loops)},
      {"optimisations", double(c.optimisations)},
      {"queries", double(stats_.queries)},
      {"queries_failed", double(stats_.queries_failed)},
      {"peer_candidates_without_scan",
       double(stats_.peer_candidates_without_scan)},
      {"slam_ms_per_keyframe", stats_.slam_ms / c.keyframes},
      {"query_ms_per_keyframe", stats_.query_ms / c.keyframes},
  };
  for (const auto& [name, value] : numbers) {
    fields[name].set_number_value(value);
  }
  auto& anchors = *fields["anchors"].mutable_struct_value()->mutable_fields();
  for (const std::string& peer : slam_.Peers()) {
    const std::optional<Pose2> frame = slam_.FrameInPeer(peer);
    if (!frame) continue;
    auto& a = *anchors[peer].mutable_struct_value()->mutable_fields();
    a["x"].set_number_value(frame->x);
    a["y"].set_number_value(frame->y);
    a["yaw"].set_number_value(frame->yaw);
    Trajectory in_peer = trajectory;
    const Eigen::Isometry3d t = PlanarPose(frame->x, frame->y, frame->yaw);
    for (StampedPose& p : in_peer) p.pose = t * p.pose;
    if (absl::Status s =
            files::WriteFile(absl::StrCat(dir, "/trajectory_in_", peer, ".tum"),
                             FormatTrajectory(in_peer, TrajectoryFormat::kTum));
        !s.ok()) {
      return s;
    }
  }
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.add_whitespace = true;
  if (!google::protobuf::util::MessageToJsonString(report, &json, print).ok()) {
    return absl::InternalError("cannot print slam.json");
  }
  return files::WriteFile(dir + "/slam.json", json);
}

}  // namespace fleetmem::slam
