#include "services/storage/record_codec.h"

#include <algorithm>
#include <optional>
#include <variant>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "google/protobuf/arena.h"
#include "services/core/absl_view.h"
#include "services/core/seq_set.h"
#include "services/storage/keys.h"
#include "services/storage/records.pb.h"

namespace fleetmem::storage {
namespace {

absl::Status Corrupt(std::string_view key, std::string_view what) {
  return absl::DataLossError(
      absl::StrCat("corrupt record at ", keys::Describe(key), ": ", V(what)));
}

template <typename Message>
absl::Status Parse(std::string_view key, std::string_view value,
                   Message* message) {
  if (!message->ParseFromArray(value.data(), static_cast<int>(value.size()))) {
    return Corrupt(key, absl::StrCat("cannot parse ", message->GetTypeName()));
  }
  return absl::OkStatus();
}

// The key's suffix, if `key` has `tag` (the fleet is not checked: the store
// only reads keys inside the fleet's range).
std::optional<std::string_view> SuffixOf(std::string_view key, keys::Tag tag) {
  const std::optional<keys::ParsedKey> parsed = keys::Parse(key);
  if (!parsed || parsed->tag != tag) return std::nullopt;
  return parsed->suffix;
}

void ToProto(const core::Place& place, Place* out) {
  out->set_x(place.x);
  out->set_y(place.y);
  out->set_z(place.z);
  out->set_yaw(place.yaw);
}

core::Place FromProto(const Place& place) {
  return core::Place{place.x(), place.y(), place.z(), place.yaw()};
}

}  // namespace

std::string EncodeMeta(const engine::FleetMeta& meta) {
  Meta record;
  record.set_code_dimension(meta.code_dimension);
  record.set_encoder_version(meta.encoder_version);
  record.set_next_cluster_id(meta.next_cluster_id);
  record.set_next_event_id(meta.next_event_id);
  record.set_consolidations(meta.consolidations);
  record.set_clusters_forgotten(meta.clusters_forgotten);
  record.set_first_event_id(meta.first_event_id);
  record.set_log_position(meta.log_position);
  return record.SerializeAsString();
}

absl::StatusOr<engine::FleetMeta> DecodeMeta(std::string_view key,
                                             std::string_view value) {
  Meta record;
  if (absl::Status status = Parse(key, value, &record); !status.ok()) {
    return status;
  }
  engine::FleetMeta meta;
  meta.code_dimension = record.code_dimension();
  meta.encoder_version = record.encoder_version();
  meta.next_cluster_id = record.next_cluster_id();
  meta.next_event_id = record.next_event_id();
  meta.consolidations = record.consolidations();
  meta.clusters_forgotten = record.clusters_forgotten();
  meta.first_event_id = std::max<uint64_t>(1, record.first_event_id());
  meta.log_position = record.log_position();
  return meta;
}

namespace {

void ToRecord(const core::MemoryTrace& trace, Trace* record) {
  record->set_robot_id(trace.robot_id);
  record->set_seq(trace.seq);
  record->set_domain(trace.domain);
  record->mutable_code()->Add(trace.code.begin(), trace.code.end());
  ToProto(trace.place, record->mutable_place());
  record->set_reward(trace.reward);
  record->set_reward_external(trace.reward_external);
  record->set_reward_internal(trace.reward_internal);
  record->set_timestamp_ns(trace.timestamp_ns);
  record->set_replay_count(trace.replay_count);
  record->set_encoder_version(trace.encoder_version);
  record->set_cluster_id(trace.cluster_id);
  record->set_attachment(trace.attachment);
}

core::MemoryTrace FromRecord(const Trace& record) {
  core::MemoryTrace trace;
  trace.robot_id = record.robot_id();
  trace.seq = record.seq();
  trace.domain = record.domain();
  trace.code.assign(record.code().begin(), record.code().end());
  trace.place = FromProto(record.place());
  trace.reward = record.reward();
  trace.reward_external = record.reward_external();
  trace.reward_internal = record.reward_internal();
  trace.timestamp_ns = record.timestamp_ns();
  trace.replay_count = record.replay_count();
  trace.encoder_version = record.encoder_version();
  trace.cluster_id = record.cluster_id();
  trace.attachment = record.attachment();
  return trace;
}

}  // namespace

std::string EncodeTrace(const core::MemoryTrace& trace) {
  Trace record;
  ToRecord(trace, &record);
  return record.SerializeAsString();
}

absl::StatusOr<core::MemoryTrace> DecodeTrace(std::string_view key,
                                              std::string_view value) {
  Trace record;
  if (absl::Status status = Parse(key, value, &record); !status.ok()) {
    return status;
  }
  std::optional<std::string_view> suffix = SuffixOf(key, keys::Tag::kTrace);
  if (!suffix) suffix = SuffixOf(key, keys::Tag::kPending);
  const std::optional<core::TraceKey> key_of_record =
      suffix ? keys::ParseTraceSuffix(*suffix) : std::nullopt;
  if (!key_of_record || key_of_record->robot_id != record.robot_id() ||
      key_of_record->seq != record.seq()) {
    return Corrupt(key, "trace does not match its key");
  }
  return FromRecord(record);
}

struct LoggedRecordBytes::Impl {
  google::protobuf::Arena arena;
  LoggedRecord* record = nullptr;
  size_t size = 0;
};

namespace {

// Fills `out` with `record` (the traces copied into the arena's message).
struct ToLoggedRecord {
  LoggedRecord* out;
  void operator()(const engine::UploadRecord& upload) const {
    out->mutable_traces()->Reserve(static_cast<int>(upload.traces.size()));
    for (const core::MemoryTrace& trace : upload.traces) {
      ToRecord(trace, out->add_traces());
    }
  }
  void operator()(const engine::ConsolidateRecord&) const {
    out->mutable_consolidate();
  }
  void operator()(const engine::SampleReplayRecord& call) const {
    LoggedSampleReplay* sample = out->mutable_sample_replay();
    sample->set_robot_id(std::string(call.robot_id));
    sample->set_count(call.count);
    sample->set_request_id(std::string(call.request_id));
  }
};

// The record `logged` holds; nullopt when it holds none (no trace and no
// call) or both.
std::optional<engine::StoredRecord> FromLoggedRecord(
    const LoggedRecord& logged) {
  const int calls =
      (logged.has_consolidate() ? 1 : 0) + (logged.has_sample_replay() ? 1 : 0);
  if (calls + (logged.traces().empty() ? 0 : 1) != 1) return std::nullopt;
  if (logged.has_consolidate()) return engine::ConsolidateRecord{};
  if (logged.has_sample_replay()) {
    const LoggedSampleReplay& call = logged.sample_replay();
    return engine::SampleReplayCall{call.robot_id(), call.count(),
                                    call.request_id()};
  }
  std::vector<core::MemoryTrace> traces;
  traces.reserve(logged.traces_size());
  for (const Trace& trace : logged.traces()) {
    traces.push_back(FromRecord(trace));
  }
  return traces;
}

}  // namespace

LoggedRecordBytes::LoggedRecordBytes(const engine::LogRecord& record)
    : impl_(std::make_unique<Impl>()) {
  impl_->record =
      google::protobuf::Arena::CreateMessage<LoggedRecord>(&impl_->arena);
  std::visit(ToLoggedRecord{impl_->record}, record);
  impl_->size = impl_->record->ByteSizeLong();
}

LoggedRecordBytes::~LoggedRecordBytes() = default;
LoggedRecordBytes::LoggedRecordBytes(LoggedRecordBytes&&) noexcept = default;
LoggedRecordBytes& LoggedRecordBytes::operator=(LoggedRecordBytes&&) noexcept =
    default;

size_t LoggedRecordBytes::size() const { return impl_->size; }

void LoggedRecordBytes::WriteTo(char* out) const {
  impl_->record->SerializeWithCachedSizesToArray(
      reinterpret_cast<uint8_t*>(out));
}

std::string EncodeLoggedRecord(const engine::LogRecord& record) {
  const LoggedRecordBytes bytes(record);
  std::string out(bytes.size(), '\0');
  bytes.WriteTo(out.data());
  return out;
}

absl::StatusOr<engine::LogEntry> DecodeLoggedUpload(std::string_view key,
                                                    std::string_view value) {
  LoggedRecord record;
  if (absl::Status status = Parse(key, value, &record); !status.ok()) {
    return status;
  }
  const std::optional<std::string_view> suffix = SuffixOf(key, keys::Tag::kLog);
  const std::optional<uint64_t> sequence =
      suffix ? keys::ParseIdSuffix(*suffix) : std::nullopt;
  if (!sequence || *sequence == 0 || record.traces().empty()) {
    return Corrupt(key, "log entry does not match its key or holds no trace");
  }
  engine::LogEntry entry;
  entry.sequence = *sequence;
  entry.record = *FromLoggedRecord(record);
  return entry;
}

absl::StatusOr<engine::StoredRecord> DecodeLoggedRecord(
    std::string_view where, std::string_view value) {
  LoggedRecord record;
  std::optional<engine::StoredRecord> decoded;
  if (record.ParseFromArray(value.data(), static_cast<int>(value.size()))) {
    decoded = FromLoggedRecord(record);
  }
  if (!decoded.has_value()) {
    return absl::DataLossError(absl::StrCat(
        V(where), ": the entry does not parse or holds no record"));
  }
  return *std::move(decoded);
}

std::string EncodeCluster(const StoredCluster& cluster) {
  Cluster record;
  record.set_id(cluster.id);
  record.set_robot_id(cluster.robot_id);
  record.mutable_centroid()->Add(cluster.centroid.begin(),
                                 cluster.centroid.end());
  for (const core::TraceKey& member : cluster.members) {
    TraceKey* out = record.add_members();
    out->set_robot_id(member.robot_id);
    out->set_seq(member.seq);
  }
  return record.SerializeAsString();
}

absl::StatusOr<StoredCluster> DecodeCluster(std::string_view key,
                                            std::string_view value) {
  Cluster record;
  if (absl::Status status = Parse(key, value, &record); !status.ok()) {
    return status;
  }
  const std::optional<std::string_view> suffix =
      SuffixOf(key, keys::Tag::kCluster);
  const std::optional<uint64_t> id =
      suffix ? keys::ParseIdSuffix(*suffix) : std::nullopt;
  if (!id || *id != record.id()) {
    return Corrupt(key, "cluster does not match its key");
  }
  StoredCluster cluster;
  cluster.id = record.id();
  cluster.robot_id = record.robot_id();
  cluster.centroid.assign(record.centroid().begin(), record.centroid().end());
  cluster.members.reserve(record.members_size());
  for (const TraceKey& member : record.members()) {
    cluster.members.push_back(core::TraceKey{member.robot_id(), member.seq()});
  }
  return cluster;
}

std::string EncodeRobot(const engine::RobotRecord& robot) {
  Robot record;
  record.set_robot_id(robot.robot_id);
  for (const core::SeqSet::Interval& interval : robot.received.Intervals()) {
    SeqInterval* out = record.add_received();
    out->set_first(interval.first);
    out->set_last(interval.second);
  }
  record.set_replayed(robot.replayed);
  record.set_last_sample_request_id(robot.last_sample_request_id);
  for (const core::TraceKey& key : robot.last_sample) {
    TraceKey* out = record.add_last_sample();
    out->set_robot_id(key.robot_id);
    out->set_seq(key.seq);
  }
  return record.SerializeAsString();
}

absl::StatusOr<engine::RobotRecord> DecodeRobot(std::string_view key,
                                                std::string_view value) {
  Robot record;
  if (absl::Status status = Parse(key, value, &record); !status.ok()) {
    return status;
  }
  const std::optional<std::string_view> suffix =
      SuffixOf(key, keys::Tag::kRobot);
  if (!suffix || *suffix != record.robot_id()) {
    return Corrupt(key, "robot does not match its key");
  }
  std::vector<core::SeqSet::Interval> intervals;
  intervals.reserve(record.received_size());
  for (const SeqInterval& interval : record.received()) {
    if (interval.first() > interval.last()) {
      return Corrupt(key, "interval with first > last");
    }
    intervals.emplace_back(interval.first(), interval.last());
  }
  engine::RobotRecord robot;
  robot.robot_id = record.robot_id();
  robot.received = core::SeqSet::FromIntervals(intervals);
  robot.replayed = record.replayed();
  robot.last_sample_request_id = record.last_sample_request_id();
  robot.last_sample.reserve(record.last_sample_size());
  for (const TraceKey& key : record.last_sample()) {
    robot.last_sample.push_back(core::TraceKey{key.robot_id(), key.seq()});
  }
  return robot;
}

std::string EncodeEvent(const core::MemoryEvent& event) {
  Event record;
  record.set_id(event.id);
  switch (event.type) {
    case core::EventType::kClusterAdded:
      record.set_type(EVENT_TYPE_CLUSTER_ADDED);
      break;
    case core::EventType::kClusterForgotten:
      record.set_type(EVENT_TYPE_CLUSTER_FORGOTTEN);
      break;
    case core::EventType::kClusterMerged:
      record.set_type(EVENT_TYPE_CLUSTER_MERGED);
      record.set_merged_into(event.merged_into);
      record.set_traces_dropped(event.traces_dropped);
      break;
  }
  record.set_cluster_id(event.cluster_id);
  record.set_trace_count(event.trace_count);
  record.set_robot_id(event.robot_id);
  record.set_domain(event.domain);
  ToProto(event.centroid_place, record.mutable_centroid_place());
  record.set_mean_reward(event.mean_reward);
  record.set_timestamp_ns(event.timestamp_ns);
  return record.SerializeAsString();
}

absl::StatusOr<core::MemoryEvent> DecodeEvent(std::string_view key,
                                              std::string_view value) {
  Event record;
  if (absl::Status status = Parse(key, value, &record); !status.ok()) {
    return status;
  }
  const std::optional<std::string_view> suffix =
      SuffixOf(key, keys::Tag::kEvent);
  const std::optional<uint64_t> id =
      suffix ? keys::ParseIdSuffix(*suffix) : std::nullopt;
  if (!id || *id != record.id()) {
    return Corrupt(key, "event does not match its key");
  }
  core::MemoryEvent event;
  switch (record.type()) {
    case EVENT_TYPE_CLUSTER_ADDED:
      event.type = core::EventType::kClusterAdded;
      break;
    case EVENT_TYPE_CLUSTER_FORGOTTEN:
      event.type = core::EventType::kClusterForgotten;
      break;
    case EVENT_TYPE_CLUSTER_MERGED:
      event.type = core::EventType::kClusterMerged;
      event.merged_into = record.merged_into();
      event.traces_dropped = record.traces_dropped();
      break;
    default:
      return Corrupt(key, absl::StrCat("unknown event type ", record.type()));
  }
  event.id = record.id();
  event.cluster_id = record.cluster_id();
  event.trace_count = record.trace_count();
  event.robot_id = record.robot_id();
  event.domain = record.domain();
  event.centroid_place = FromProto(record.centroid_place());
  event.mean_reward = record.mean_reward();
  event.timestamp_ns = record.timestamp_ns();
  return event;
}

absl::Status AssembleCluster(
    std::string_view key, StoredCluster stored,
    std::map<core::TraceKey, core::MemoryTrace>* traces,
    std::vector<core::Cluster>* clusters) {
  core::Cluster cluster;
  cluster.id = stored.id;
  cluster.robot_id = std::move(stored.robot_id);
  cluster.centroid = std::move(stored.centroid);
  cluster.traces.reserve(stored.members.size());
  for (const core::TraceKey& member : stored.members) {
    auto trace = traces->find(member);
    if (trace == traces->end() || trace->second.cluster_id != stored.id) {
      return Corrupt(key,
                     absl::StrCat("member ", member.robot_id, "/", member.seq,
                                  " has no trace of this cluster"));
    }
    cluster.traces.push_back(std::move(trace->second));
    traces->erase(trace);
  }
  clusters->push_back(std::move(cluster));
  return absl::OkStatus();
}

}  // namespace fleetmem::storage
