#include "services/storage/record_codec.h"

#include <algorithm>
#include <bit>
#include <cstring>
#include <optional>
#include <tuple>
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

namespace {

void ToRecord(const engine::FleetSettings& settings, StoredSettings* out) {
  const core::MemoryOptions& memory = settings.memory;
  out->set_place_unit(settings.place_unit);
  out->set_clusters_per_batch(memory.clusters_per_batch);
  out->set_max_traces_per_cluster(memory.max_traces_per_cluster);
  out->set_max_clusters(memory.max_clusters);
  out->set_replay_decay(memory.replay_decay);
  out->set_reward_floor(memory.reward_floor);
  out->set_spatial_scale_m(memory.spatial_scale_m);
  out->set_clustering(memory.clustering);
  out->set_merge_on_forget(memory.merge_on_forget);
  out->set_kmeans_max_iterations(memory.kmeans_max_iterations);
  out->set_seed(memory.seed);
  out->set_forgetting_exact_below(memory.forgetting_exact_below);
  out->set_refresh_pair_radius(memory.refresh_pair_radius);
  out->set_refresh_uniform(memory.refresh_uniform);
  out->set_max_age_seconds(settings.max_age_seconds);
  out->set_max_traces_per_robot(settings.max_traces_per_robot);
  out->set_index_kind(static_cast<int32_t>(settings.index.kind));
  out->set_hnsw_m(settings.index.hnsw_m);
  out->set_hnsw_ef_search(settings.index.hnsw_ef_search);
  out->set_hnsw_codes(static_cast<int32_t>(settings.index.hnsw_codes));
}

void ToRecord(const core::ReadFilter& filter, LoggedReadFilter* out) {
  for (const std::string& robot_id : filter.robot_ids) {
    out->add_robot_ids(robot_id);
  }
  for (const std::string& domain : filter.domains) out->add_domains(domain);
  if (filter.time_from_ns) out->set_time_from_ns(*filter.time_from_ns);
  if (filter.time_to_ns) out->set_time_to_ns(*filter.time_to_ns);
  out->set_encoder_version(filter.encoder_version);
}

core::ReadFilter FromRecord(const LoggedReadFilter& stored) {
  core::ReadFilter filter;
  filter.robot_ids.assign(stored.robot_ids().begin(), stored.robot_ids().end());
  filter.domains.assign(stored.domains().begin(), stored.domains().end());
  if (stored.has_time_from_ns()) filter.time_from_ns = stored.time_from_ns();
  if (stored.has_time_to_ns()) filter.time_to_ns = stored.time_to_ns();
  filter.encoder_version = stored.encoder_version();
  return filter;
}

engine::FleetSettings FromRecord(const StoredSettings& stored) {
  engine::FleetSettings settings;
  core::MemoryOptions& memory = settings.memory;
  settings.place_unit = stored.place_unit();
  memory.clusters_per_batch = stored.clusters_per_batch();
  memory.max_traces_per_cluster = stored.max_traces_per_cluster();
  memory.max_clusters = stored.max_clusters();
  memory.replay_decay = stored.replay_decay();
  memory.reward_floor = stored.reward_floor();
  memory.spatial_scale_m = stored.spatial_scale_m();
  memory.clustering = stored.clustering();
  memory.merge_on_forget = stored.merge_on_forget();
  memory.kmeans_max_iterations = stored.kmeans_max_iterations();
  memory.seed = stored.seed();
  memory.forgetting_exact_below = stored.forgetting_exact_below();
  memory.refresh_pair_radius = stored.refresh_pair_radius();
  memory.refresh_uniform = stored.refresh_uniform();
  settings.max_age_seconds = stored.max_age_seconds();
  settings.max_traces_per_robot = stored.max_traces_per_robot();
  // A kind this version does not know: the server's index.
  const int kind = stored.index_kind();
  settings.index.kind =
      kind >= 0 && kind <= static_cast<int>(engine::IndexSettings::Kind::kAuto)
          ? static_cast<engine::IndexSettings::Kind>(kind)
          : engine::IndexSettings::Kind::kServer;
  settings.index.hnsw_m = stored.hnsw_m();
  settings.index.hnsw_ef_search = stored.hnsw_ef_search();
  const int codes = stored.hnsw_codes();
  settings.index.hnsw_codes =
      codes >= 0 &&
              codes <= static_cast<int>(engine::IndexSettings::Codes::kFloat)
          ? static_cast<engine::IndexSettings::Codes>(codes)
          : engine::IndexSettings::Codes::kServer;
  return settings;
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
  if (meta.settings) ToRecord(*meta.settings, record.mutable_settings());
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
  if (record.has_settings()) meta.settings = FromRecord(record.settings());
  if (meta.settings) {
    if (absl::Status valid = core::ValidateMemoryOptions(meta.settings->memory);
        !valid.ok()) {
      return Corrupt(key, absl::StrCat("settings: ", valid.message()));
    }
  }
  return meta;
}

namespace {

void ToRecord(const core::MemoryTrace& trace, Trace* record,
              bool with_code = true) {
  record->set_robot_id(trace.robot_id);
  record->set_seq(trace.seq);
  record->set_domain(trace.domain);
  if (with_code) {
    record->mutable_code()->Add(trace.code.begin(), trace.code.end());
  }
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

std::string EncodeTraceWithoutCode(const core::MemoryTrace& trace) {
  Trace record;
  ToRecord(trace, &record, /*with_code=*/false);
  return record.SerializeAsString();
}

// Codes are written as the floats' bytes in memory.
static_assert(std::endian::native == std::endian::little,
              "codes are stored little-endian: this build assumes a "
              "little-endian machine");

std::string EncodeCode(std::span<const float> code) {
  return std::string(reinterpret_cast<const char*>(code.data()),
                     code.size() * sizeof(float));
}

absl::Status DecodeCode(std::string_view key, std::string_view value,
                        std::vector<float>* code) {
  if (value.empty() || value.size() % sizeof(float) != 0) {
    return Corrupt(key, absl::StrCat("a code of ", value.size(),
                                     " bytes is not a whole number of floats"));
  }
  code->resize(value.size() / sizeof(float));
  std::memcpy(code->data(), value.data(), value.size());
  return absl::OkStatus();
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
    if (call.filter != nullptr) {
      ToRecord(*call.filter, sample->mutable_filter());
    }
  }
  void operator()(const engine::DeleteTracesRecord& call) const {
    LoggedDeleteTraces* selection = out->mutable_delete_traces();
    const core::TraceFilter& filter = call.filter;
    selection->set_robot_id(filter.robot_id);
    selection->set_domain(filter.domain);
    if (filter.seq_first) selection->set_seq_first(*filter.seq_first);
    if (filter.seq_last) selection->set_seq_last(*filter.seq_last);
    if (filter.time_from_ns) selection->set_time_from_ns(*filter.time_from_ns);
    if (filter.time_to_ns) selection->set_time_to_ns(*filter.time_to_ns);
  }
  void operator()(const engine::CreateFleetRecord& call) const {
    LoggedCreateFleet* create = out->mutable_create_fleet();
    create->set_code_dimension(call.code_dimension);
    create->set_encoder_version(call.encoder_version);
    ToRecord(call.settings, create->mutable_settings());
  }
  void operator()(const engine::EnforceRetentionRecord& call) const {
    out->mutable_enforce_retention()->set_now_ns(call.now_ns);
  }
  void operator()(const engine::DeleteFleetRecord&) const {
    out->mutable_delete_fleet();
  }
  void operator()(const engine::UpdateFleetRecord& call) const {
    LoggedUpdateFleet* update = out->mutable_update_fleet();
    const engine::FleetSettingsUpdate& u = call.update;
    if (u.clusters_per_batch) {
      update->set_clusters_per_batch(*u.clusters_per_batch);
    }
    if (u.max_traces_per_cluster) {
      update->set_max_traces_per_cluster(*u.max_traces_per_cluster);
    }
    if (u.max_clusters) update->set_max_clusters(*u.max_clusters);
    if (u.replay_decay) update->set_replay_decay(*u.replay_decay);
    if (u.merge_on_forget) update->set_merge_on_forget(*u.merge_on_forget);
    if (u.refresh_pair_radius) {
      update->set_refresh_pair_radius(*u.refresh_pair_radius);
    }
    if (u.refresh_uniform) update->set_refresh_uniform(*u.refresh_uniform);
    if (u.max_age_seconds) update->set_max_age_seconds(*u.max_age_seconds);
    if (u.max_traces_per_robot) {
      update->set_max_traces_per_robot(*u.max_traces_per_robot);
    }
  }
  void operator()(const engine::UpdateRewardsRecord& call) const {
    LoggedUpdateRewards* rewards = out->mutable_update_rewards();
    for (const core::RewardUpdate& update : call.updates) {
      LoggedRewardUpdate* one = rewards->add_updates();
      one->set_robot_id(update.key.robot_id);
      one->set_seq(update.key.seq);
      one->set_reward_external(update.reward_external);
      one->set_reward_internal(update.reward_internal);
    }
  }
};

engine::DeleteTracesRecord FromLogged(const LoggedDeleteTraces& logged) {
  engine::DeleteTracesRecord call;
  core::TraceFilter& filter = call.filter;
  filter.robot_id = logged.robot_id();
  filter.domain = logged.domain();
  if (logged.has_seq_first()) filter.seq_first = logged.seq_first();
  if (logged.has_seq_last()) filter.seq_last = logged.seq_last();
  if (logged.has_time_from_ns()) filter.time_from_ns = logged.time_from_ns();
  if (logged.has_time_to_ns()) filter.time_to_ns = logged.time_to_ns();
  return call;
}

engine::CreateFleetRecord FromLogged(const LoggedCreateFleet& logged) {
  return engine::CreateFleetRecord{logged.code_dimension(),
                                   logged.encoder_version(),
                                   FromRecord(logged.settings())};
}

engine::UpdateFleetRecord FromLogged(const LoggedUpdateFleet& logged) {
  engine::UpdateFleetRecord call;
  engine::FleetSettingsUpdate& u = call.update;
  if (logged.has_clusters_per_batch()) {
    u.clusters_per_batch = logged.clusters_per_batch();
  }
  if (logged.has_max_traces_per_cluster()) {
    u.max_traces_per_cluster = logged.max_traces_per_cluster();
  }
  if (logged.has_max_clusters()) u.max_clusters = logged.max_clusters();
  if (logged.has_replay_decay()) u.replay_decay = logged.replay_decay();
  if (logged.has_merge_on_forget()) {
    u.merge_on_forget = logged.merge_on_forget();
  }
  if (logged.has_refresh_pair_radius()) {
    u.refresh_pair_radius = logged.refresh_pair_radius();
  }
  if (logged.has_refresh_uniform()) {
    u.refresh_uniform = logged.refresh_uniform();
  }
  if (logged.has_max_age_seconds()) {
    u.max_age_seconds = logged.max_age_seconds();
  }
  if (logged.has_max_traces_per_robot()) {
    u.max_traces_per_robot = logged.max_traces_per_robot();
  }
  return call;
}

engine::UpdateRewardsCall FromLogged(const LoggedUpdateRewards& logged) {
  engine::UpdateRewardsCall call;
  call.updates.reserve(logged.updates_size());
  for (const LoggedRewardUpdate& one : logged.updates()) {
    call.updates.push_back(
        core::RewardUpdate{core::TraceKey{one.robot_id(), one.seq()},
                           one.reward_external(), one.reward_internal()});
  }
  return call;
}

// The record `logged` holds; nullopt when it holds none (no trace and no
// call) or both.
std::optional<engine::StoredRecord> FromLoggedRecord(
    const LoggedRecord& logged) {
  const int calls = (logged.has_consolidate() ? 1 : 0) +
                    (logged.has_sample_replay() ? 1 : 0) +
                    (logged.has_delete_traces() ? 1 : 0) +
                    (logged.has_update_rewards() ? 1 : 0) +
                    (logged.has_create_fleet() ? 1 : 0) +
                    (logged.has_update_fleet() ? 1 : 0) +
                    (logged.has_enforce_retention() ? 1 : 0) +
                    (logged.has_delete_fleet() ? 1 : 0);
  if (calls + (logged.traces().empty() ? 0 : 1) != 1) return std::nullopt;
  if (logged.has_consolidate()) return engine::ConsolidateRecord{};
  if (logged.has_delete_fleet()) return engine::DeleteFleetRecord{};
  if (logged.has_delete_traces()) return FromLogged(logged.delete_traces());
  if (logged.has_update_rewards()) return FromLogged(logged.update_rewards());
  if (logged.has_create_fleet()) return FromLogged(logged.create_fleet());
  if (logged.has_update_fleet()) return FromLogged(logged.update_fleet());
  if (logged.has_enforce_retention()) {
    return engine::EnforceRetentionRecord{logged.enforce_retention().now_ns()};
  }
  if (logged.has_sample_replay()) {
    const LoggedSampleReplay& call = logged.sample_replay();
    return engine::SampleReplayCall{call.robot_id(), call.count(),
                                    call.request_id(),
                                    FromRecord(call.filter())};
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
    case core::EventType::kTracesDeleted:
      record.set_type(EVENT_TYPE_TRACES_DELETED);
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
    case EVENT_TYPE_TRACES_DELETED:
      event.type = core::EventType::kTracesDeleted;
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

namespace {

bool KeyLess(const core::MemoryTrace& a, const core::MemoryTrace& b) {
  return std::tie(a.robot_id, a.seq) < std::tie(b.robot_id, b.seq);
}

// True if `trace` comes before `key` in key order.
bool KeyBefore(const core::MemoryTrace& trace, const core::TraceKey& key) {
  return std::tie(trace.robot_id, trace.seq) < std::tie(key.robot_id, key.seq);
}

}  // namespace

void TraceTable::Add(core::MemoryTrace trace) {
  if (!traces_.empty() && !KeyLess(traces_.back(), trace)) sorted_ = false;
  traces_.push_back(std::move(trace));
  taken_.push_back(false);
  ++left_;
}

void TraceTable::Sort() {
  // Stable: of a key added twice, the first stays first and is taken.
  std::stable_sort(traces_.begin(), traces_.end(), KeyLess);
  sorted_ = true;
}

size_t TraceTable::LowerBound(const core::TraceKey& key) {
  const size_t n = traces_.size();
  auto before = [&](size_t i) { return KeyBefore(traces_[i], key); };
  // The answer lies in [lo, hi]; gallop from the hint to bracket it, then
  // search the bracket.
  const size_t at = std::min(hint_, n);
  size_t lo = 0;
  size_t hi = n;
  if (at < n && before(at)) {
    lo = at + 1;
    for (size_t step = 1; at + step < n; step *= 2) {
      if (!before(at + step)) {
        hi = at + step;
        break;
      }
      lo = at + step + 1;
    }
  } else {
    hi = at;
    for (size_t step = 1; step <= at; step *= 2) {
      if (before(at - step)) {
        lo = at - step + 1;
        break;
      }
      hi = at - step;
    }
  }
  const auto first = std::lower_bound(traces_.begin() + lo,
                                      traces_.begin() + hi, key, KeyBefore);
  hint_ = static_cast<size_t>(first - traces_.begin());
  return hint_;
}

std::optional<core::MemoryTrace> TraceTable::Take(const core::TraceKey& key,
                                                  uint64_t cluster_id) {
  if (!sorted_) Sort();
  const size_t at = LowerBound(key);
  if (at == traces_.size()) return std::nullopt;
  core::MemoryTrace& found = traces_[at];
  if (found.robot_id != key.robot_id || found.seq != key.seq ||
      found.cluster_id != cluster_id) {
    return std::nullopt;
  }
  if (taken_[at]) return std::nullopt;
  taken_[at] = true;
  --left_;
  core::MemoryTrace taken = std::move(found);
  // The slot keeps its key: the table stays sorted for the next search.
  found.robot_id = taken.robot_id;
  found.seq = taken.seq;
  return taken;
}

const core::MemoryTrace* TraceTable::AnyLeft() const {
  if (left_ == 0) return nullptr;
  for (size_t i = 0; i < traces_.size(); ++i) {
    if (!taken_[i]) return &traces_[i];
  }
  return nullptr;
}

absl::Status TraceTable::ForEach(
    absl::FunctionRef<absl::Status(core::MemoryTrace&)> visit) {
  if (!sorted_) Sort();
  for (size_t i = 0; i < traces_.size(); ++i) {
    if (taken_[i]) continue;
    if (absl::Status status = visit(traces_[i]); !status.ok()) return status;
  }
  return absl::OkStatus();
}

absl::Status AssembleCluster(std::string_view key, StoredCluster stored,
                             TraceTable* traces,
                             std::vector<core::Cluster>* clusters) {
  core::Cluster cluster;
  cluster.id = stored.id;
  cluster.robot_id = std::move(stored.robot_id);
  cluster.centroid = std::move(stored.centroid);
  cluster.traces.reserve(stored.members.size());
  for (const core::TraceKey& member : stored.members) {
    std::optional<core::MemoryTrace> trace = traces->Take(member, stored.id);
    if (!trace) {
      return Corrupt(key,
                     absl::StrCat("member ", member.robot_id, "/", member.seq,
                                  " has no trace of this cluster"));
    }
    cluster.traces.push_back(std::move(*trace));
  }
  clusters->push_back(std::move(cluster));
  return absl::OkStatus();
}

}  // namespace fleetmem::storage
