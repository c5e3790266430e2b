#include "services/transport/proto_convert.h"

#include <algorithm>
#include <climits>
#include <cstdint>
#include <cstring>

#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::transport {

std::vector<core::MemoryTrace> UploadedTracesFromProto(
    const google::protobuf::RepeatedPtrField<v1::MemoryTrace>& traces) {
  std::vector<core::MemoryTrace> out;
  out.reserve(traces.size());
  for (const v1::MemoryTrace& trace : traces) {
    core::MemoryTrace& added = out.emplace_back(TraceFromProto(trace));
    added.replay_count = 0;
    added.cluster_id = 0;
  }
  return out;
}

namespace {

v1::MemoryEvent::Type EventTypeToProto(core::EventType type) {
  switch (type) {
    case core::EventType::kClusterAdded:
      return v1::MemoryEvent::CLUSTER_ADDED;
    case core::EventType::kClusterForgotten:
      return v1::MemoryEvent::CLUSTER_FORGOTTEN;
    case core::EventType::kClusterMerged:
      return v1::MemoryEvent::CLUSTER_MERGED;
    case core::EventType::kTracesDeleted:
      return v1::MemoryEvent::TRACES_DELETED;
  }
  return v1::MemoryEvent::TYPE_UNSPECIFIED;
}

}  // namespace

void EventToProto(const core::MemoryEvent& event, v1::MemoryEvent* out) {
  out->set_id(event.id);
  out->set_type(EventTypeToProto(event.type));
  out->set_cluster_id(event.cluster_id);
  out->set_trace_count(event.trace_count);
  out->set_robot_id(event.robot_id);
  out->set_domain(event.domain);
  PlaceToProto(event.centroid_place, out->mutable_centroid_pose());
  out->set_mean_reward(event.mean_reward);
  out->set_timestamp_ns(event.timestamp_ns);
  out->set_merged_into(event.merged_into);
  out->set_traces_dropped(event.traces_dropped);
}

engine::PlaceQuery QueryFromProto(const v1::QueryPlaceRequest& request) {
  engine::PlaceQuery query;
  query.code.assign(request.code().begin(), request.code().end());
  query.k = request.k();
  query.near = PlaceFromProto(request.near());
  query.radius_m = request.radius_m();
  query.filter = api::ReadFilterFromProto(request.filter());
  return query;
}

void AddUploadResult(const engine::UploadResult& result,
                     v1::UploadTracesResponse* out) {
  out->set_accepted(out->accepted() + result.accepted);
  out->set_duplicates(out->duplicates() + result.duplicates);
  out->set_consolidations(out->consolidations() + result.consolidations);
}

void ConsolidateResultToProto(const engine::ConsolidateResult& result,
                              v1::ConsolidateResponse* out) {
  out->set_consolidated_traces(result.consolidated_traces);
  out->set_downsampled_traces(result.downsampled_traces);
  out->set_clusters_added(result.clusters_added);
  out->set_clusters_forgotten(result.clusters_forgotten);
  out->set_clusters(result.clusters);
  out->set_traces(result.traces);
}

void SampledTracesToProto(std::span<const core::MemoryTrace> traces,
                          v1::SampleReplayResponse* out) {
  out->mutable_traces()->Reserve(static_cast<int>(traces.size()));
  for (const core::MemoryTrace& trace : traces) {
    TraceToProto(trace, out->add_traces());
  }
}

void TraceColumnsToProto(std::span<const core::MemoryTrace> traces,
                         v1::TraceColumns* out) {
  const size_t n = traces.size();
  const size_t dimension = n == 0 ? 0 : traces.front().code.size();
  out->set_count(static_cast<uint32_t>(n));
  out->set_code_dimension(static_cast<uint32_t>(dimension));
  std::string* codes = out->mutable_codes();
  codes->resize(n * dimension * sizeof(float));
  const int rows = static_cast<int>(n);
  out->mutable_places()->Reserve(4 * rows);
  out->mutable_rewards()->Reserve(rows);
  out->mutable_rewards_external()->Reserve(rows);
  out->mutable_rewards_internal()->Reserve(rows);
  out->mutable_seqs()->Reserve(rows);
  out->mutable_replay_counts()->Reserve(rows);
  out->mutable_cluster_ids()->Reserve(rows);
  out->mutable_timestamps_ns()->Reserve(rows);
  bool attachments = false;
  for (const core::MemoryTrace& trace : traces) {
    attachments = attachments || !trace.attachment.empty();
  }
  for (size_t i = 0; i < n; ++i) {
    const core::MemoryTrace& trace = traces[i];
    // One fleet, one dimension (the engine checks it at the upload); the
    // bytes are the host's floats: little-endian on every platform built.
    std::memcpy(codes->data() + i * dimension * sizeof(float),
                trace.code.data(),
                std::min(dimension, trace.code.size()) * sizeof(float));
    for (double value :
         {trace.place.x, trace.place.y, trace.place.z, trace.place.yaw}) {
      out->add_places(value);
    }
    out->add_rewards(trace.reward);
    out->add_rewards_external(trace.reward_external);
    out->add_rewards_internal(trace.reward_internal);
    out->add_seqs(trace.seq);
    out->add_replay_counts(trace.replay_count);
    out->add_cluster_ids(trace.cluster_id);
    out->add_timestamps_ns(trace.timestamp_ns);
    out->add_robot_ids(trace.robot_id);
    out->add_domains(trace.domain);
    out->add_encoder_versions(trace.encoder_version);
    if (attachments) out->add_attachments(trace.attachment);
  }
}

namespace {

// ImportedTracesFromColumns' shape check: every column fits `count` rows.
absl::Status CheckColumns(const v1::TraceColumns& columns) {
  const size_t n = columns.count();
  const size_t dimension = columns.code_dimension();
  const auto refuse = [&](std::string_view column, std::string_view want,
                          size_t got) {
    return absl::InvalidArgumentError(
        absl::StrCat("traces.", V(column), ": ", got, " values for ", n,
                     " rows (traces.count); want ", V(want)));
  };
  if (n > 0 && dimension == 0) {
    return absl::InvalidArgumentError(
        "traces.code_dimension: 0; want the codes' length");
  }
  if (columns.codes().size() != n * dimension * sizeof(float)) {
    return refuse("codes",
                  absl::StrCat(n * dimension * sizeof(float),
                               " bytes (count x code_dimension float32)"),
                  columns.codes().size());
  }
  const auto need = [&](std::string_view column, size_t got, size_t per_row,
                        bool optional) -> absl::Status {
    if (got == n * per_row || (optional && got == 0)) return absl::OkStatus();
    return refuse(column, absl::StrCat(n * per_row, optional ? " or none" : ""),
                  got);
  };
  for (absl::Status status : {
           need("places", columns.places_size(), 4, false),
           need("rewards", columns.rewards_size(), 1, false),
           need("robot_ids", columns.robot_ids_size(), 1, false),
           need("seqs", columns.seqs_size(), 1, false),
           need("rewards_external", columns.rewards_external_size(), 1, true),
           need("rewards_internal", columns.rewards_internal_size(), 1, true),
           need("timestamps_ns", columns.timestamps_ns_size(), 1, true),
           need("domains", columns.domains_size(), 1, true),
           need("encoder_versions", columns.encoder_versions_size(), 1, true),
           need("attachments", columns.attachments_size(), 1, true),
       }) {
    if (!status.ok()) return status;
  }
  if (columns.replay_counts_size() != 0 || columns.cluster_ids_size() != 0) {
    return absl::InvalidArgumentError(
        "traces.replay_counts and traces.cluster_ids must be empty: a "
        "fleet's replay counts and clusters are its own (the import "
        "consolidates the traces as uploads are)");
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::vector<core::MemoryTrace>> ImportedTracesFromColumns(
    const v1::TraceColumns& columns) {
  if (absl::Status checked = CheckColumns(columns); !checked.ok()) {
    return checked;
  }
  const size_t n = columns.count();
  const size_t dimension = columns.code_dimension();
  std::vector<core::MemoryTrace> traces(n);
  const char* codes = columns.codes().data();
  for (size_t i = 0; i < n; ++i) {
    core::MemoryTrace& trace = traces[i];
    const int row = static_cast<int>(i);
    trace.code.resize(dimension);
    std::memcpy(trace.code.data(), codes + i * dimension * sizeof(float),
                dimension * sizeof(float));
    trace.place.x = columns.places(4 * row);
    trace.place.y = columns.places(4 * row + 1);
    trace.place.z = columns.places(4 * row + 2);
    trace.place.yaw = columns.places(4 * row + 3);
    trace.reward = columns.rewards(row);
    trace.robot_id = columns.robot_ids(row);
    trace.seq = columns.seqs(row);
    if (columns.rewards_external_size() > 0) {
      trace.reward_external = columns.rewards_external(row);
    }
    if (columns.rewards_internal_size() > 0) {
      trace.reward_internal = columns.rewards_internal(row);
    }
    if (columns.timestamps_ns_size() > 0) {
      trace.timestamp_ns = columns.timestamps_ns(row);
    }
    if (columns.domains_size() > 0) trace.domain = columns.domains(row);
    if (columns.encoder_versions_size() > 0) {
      trace.encoder_version = columns.encoder_versions(row);
    }
    if (columns.attachments_size() > 0) {
      trace.attachment = columns.attachments(row);
    }
  }
  return traces;
}

void MatchesToProto(std::span<const engine::PlaceMatch> matches,
                    v1::QueryPlaceResponse* out) {
  out->mutable_matches()->Reserve(static_cast<int>(matches.size()));
  for (const engine::PlaceMatch& match : matches) {
    v1::PlaceMatch* added = out->add_matches();
    TraceToProto(match.trace, added->mutable_trace());
    added->set_distance(match.distance);
  }
}

void BacklogToProto(const engine::Backlog& backlog, v1::GetStatsResponse* out) {
  out->set_backlog_entries(backlog.entries);
  out->set_backlog_traces(backlog.traces);
  out->set_backlog_age_seconds(backlog.oldest_seconds);
  out->set_acknowledged_through(backlog.appended_through);
  out->set_applied_through(backlog.applied_through);
  out->set_apply_error(backlog.apply_error.ok()
                           ? std::string()
                           : backlog.apply_error.ToString());
  for (const engine::LostLogEntries& lost : backlog.lost) {
    v1::LostLogEntries* added = out->add_log_entries_lost();
    added->set_first_sequence(lost.first);
    added->set_last_sequence(lost.last);
    added->set_detail(lost.detail);
  }
}

void StatsToProto(const engine::FleetStats& stats, v1::GetStatsResponse* out) {
  out->set_traces(stats.traces);
  out->set_pending_traces(stats.pending_traces);
  out->set_clusters(stats.clusters);
  out->set_code_dimension(stats.code_dimension);
  out->set_encoder_version(stats.encoder_version);
  out->set_last_event_id(stats.last_event_id);
  out->set_consolidations(stats.consolidations);
  out->set_clusters_forgotten(stats.clusters_forgotten);
  for (const engine::RobotStats& robot : stats.robots) {
    v1::RobotStats* added = out->add_robots();
    added->set_robot_id(robot.robot_id);
    added->set_traces(robot.traces);
    added->set_pending_traces(robot.pending_traces);
    added->set_max_seq(robot.max_seq);
    added->set_received(robot.received);
    added->set_replayed(robot.replayed);
  }
  for (const engine::DomainStats& domain : stats.domains) {
    v1::DomainStats* added = out->add_domains();
    added->set_domain(domain.domain);
    added->set_traces(domain.traces);
    added->set_pending_traces(domain.pending_traces);
  }
  out->set_max_clusters(stats.max_clusters);
  out->set_max_traces_per_cluster(stats.max_traces_per_cluster);
  out->set_first_event_id(stats.first_event_id);
  out->set_unindexed_codes(stats.unindexed_codes);
  for (const auto& [limit, count] : stats.quota_rejections) {
    (*out->mutable_quota_rejections())[limit] = count;
  }
}

void FleetSummaryToProto(std::string_view fleet_id,
                         const engine::FleetStats& stats,
                         v1::FleetSummary* out) {
  out->set_fleet_id(std::string(fleet_id));
  out->set_traces(stats.traces);
  out->set_pending_traces(stats.pending_traces);
  out->set_clusters(stats.clusters);
  out->set_robots(static_cast<uint32_t>(stats.robots.size()));
  out->set_last_event_id(stats.last_event_id);
  out->set_code_dimension(stats.code_dimension);
  out->set_encoder_version(stats.encoder_version);
}

namespace {

void TracePlaceToProto(const engine::TracePlace& place, v1::TracePlace* out) {
  out->set_robot_id(place.robot_id);
  out->set_seq(place.seq);
  out->set_domain(place.domain);
  PlaceToProto(place.place, out->mutable_pose());
  out->set_reward(place.reward);
}

}  // namespace

void ClustersToProto(const engine::ClusterListing& listing,
                     v1::ListClustersResponse* out) {
  for (const engine::ClusterSummary& cluster : listing.clusters) {
    v1::ClusterSummary* summary = out->add_clusters();
    summary->set_cluster_id(cluster.cluster_id);
    summary->set_robot_id(cluster.robot_id);
    summary->set_trace_count(cluster.trace_count);
    PlaceToProto(cluster.centroid_place, summary->mutable_centroid_pose());
    summary->set_mean_reward(cluster.mean_reward);
    summary->mutable_robots()->insert(cluster.robots.begin(),
                                      cluster.robots.end());
    summary->mutable_domains()->insert(cluster.domains.begin(),
                                       cluster.domains.end());
    for (const engine::TracePlace& place : cluster.places) {
      TracePlaceToProto(place, summary->add_places());
    }
  }
  for (const engine::TracePlace& place : listing.pending) {
    TracePlaceToProto(place, out->add_pending());
  }
}

namespace {

void KeyToProto(const core::TraceKey& key, v1::TraceKey* out) {
  out->set_robot_id(key.robot_id);
  out->set_seq(key.seq);
}

}  // namespace

v1::IndexKind IndexKindToProto(engine::IndexSettings::Kind kind) {
  switch (kind) {
    case engine::IndexSettings::Kind::kExact:
      return v1::INDEX_KIND_EXACT;
    case engine::IndexSettings::Kind::kHnsw:
      return v1::INDEX_KIND_HNSW;
    case engine::IndexSettings::Kind::kAuto:
      return v1::INDEX_KIND_AUTO;
    case engine::IndexSettings::Kind::kServer:
      break;
  }
  return v1::INDEX_KIND_UNSPECIFIED;
}

engine::IndexSettings IndexFromProto(const v1::FleetSettings& settings) {
  engine::IndexSettings index;
  switch (settings.index()) {
    case v1::INDEX_KIND_EXACT:
      index.kind = engine::IndexSettings::Kind::kExact;
      break;
    case v1::INDEX_KIND_HNSW:
      index.kind = engine::IndexSettings::Kind::kHnsw;
      break;
    case v1::INDEX_KIND_AUTO:
      index.kind = engine::IndexSettings::Kind::kAuto;
      break;
    default:
      break;
  }
  index.hnsw_m = static_cast<int>(std::min<uint32_t>(settings.hnsw_m(), 1000));
  index.hnsw_ef_search = static_cast<int>(
      std::min<uint32_t>(settings.hnsw_ef_search(), 1'000'000));
  switch (settings.hnsw_codes()) {
    case v1::HNSW_CODES_INT8:
      index.hnsw_codes = engine::IndexSettings::Codes::kInt8;
      break;
    case v1::HNSW_CODES_FLOAT:
      index.hnsw_codes = engine::IndexSettings::Codes::kFloat;
      break;
    default:
      break;
  }
  return index;
}

engine::CreateFleetRecord CreateFleetFromProto(
    const v1::FleetSettings& settings, const core::MemoryOptions& defaults) {
  engine::CreateFleetRecord create;
  create.code_dimension = settings.code_dimension();
  create.encoder_version = settings.encoder_version();
  create.settings.place_unit = settings.place_unit();
  core::MemoryOptions& memory = create.settings.memory;
  memory = defaults;
  if (settings.has_clusters_per_segment()) {
    memory.clusters_per_batch = static_cast<int>(
        std::min<uint32_t>(settings.clusters_per_segment(), INT32_MAX));
  }
  if (settings.has_max_traces_per_cluster()) {
    memory.max_traces_per_cluster = static_cast<int>(
        std::min<uint32_t>(settings.max_traces_per_cluster(), INT32_MAX));
  }
  if (settings.has_max_clusters()) {
    memory.max_clusters = static_cast<int>(
        std::min<uint32_t>(settings.max_clusters(), INT32_MAX));
  }
  if (settings.has_replay_decay())
    memory.replay_decay = settings.replay_decay();
  if (settings.forgetting() != v1::FORGETTING_RULE_UNSPECIFIED) {
    memory.merge_on_forget = settings.forgetting() == v1::FORGETTING_RULE_MERGE;
  }
  if (settings.has_refresh_pair_radius()) {
    memory.refresh_pair_radius = settings.refresh_pair_radius();
  }
  if (settings.has_refresh_uniform()) {
    memory.refresh_uniform = settings.refresh_uniform();
  }
  create.settings.max_age_seconds = static_cast<int64_t>(
      std::min<uint64_t>(settings.max_age_seconds(), INT64_MAX));
  create.settings.max_traces_per_robot = settings.max_traces_per_robot();
  create.settings.index = IndexFromProto(settings);
  return create;
}

absl::StatusOr<engine::FleetSettingsUpdate> FleetUpdateFromProto(
    const v1::FleetSettings& settings, const engine::FleetInfo& current) {
  const auto fixed = [](std::string_view field, std::string_view was,
                        std::string_view asked) {
    return absl::FailedPreconditionError(absl::StrCat(
        "settings.", V(field), " is fixed at the fleet's creation (\"", V(was),
        "\"; asked \"", V(asked),
        "\"): make a new fleet with it and move the robots there (an alias "
        "switches them at once; docs/api.md, \"Encoder migration\")"));
  };
  if (settings.code_dimension() != 0 &&
      settings.code_dimension() != current.shape.code_dimension) {
    return fixed("code_dimension", absl::StrCat(current.shape.code_dimension),
                 absl::StrCat(settings.code_dimension()));
  }
  if (!settings.encoder_version().empty() &&
      settings.encoder_version() != current.shape.encoder_version) {
    return fixed("encoder_version", current.shape.encoder_version,
                 settings.encoder_version());
  }
  if (!settings.place_unit().empty() &&
      settings.place_unit() != current.settings.place_unit) {
    return fixed("place_unit", current.settings.place_unit,
                 settings.place_unit());
  }
  const engine::IndexSettings index = IndexFromProto(settings);
  const engine::IndexSettings& held = current.settings.index;
  if ((settings.index() != v1::INDEX_KIND_UNSPECIFIED &&
       index.kind != held.kind) ||
      (index.hnsw_m != 0 && index.hnsw_m != held.hnsw_m) ||
      (index.hnsw_ef_search != 0 &&
       index.hnsw_ef_search != held.hnsw_ef_search) ||
      (settings.hnsw_codes() != v1::HNSW_CODES_UNSPECIFIED &&
       index.hnsw_codes != held.hnsw_codes)) {
    return fixed("index", IndexKind_Name(IndexKindToProto(held.kind)),
                 IndexKind_Name(settings.index()));
  }
  engine::FleetSettingsUpdate update;
  if (settings.has_clusters_per_segment()) {
    update.clusters_per_batch = static_cast<int>(
        std::min<uint32_t>(settings.clusters_per_segment(), INT32_MAX));
  }
  if (settings.has_max_traces_per_cluster()) {
    update.max_traces_per_cluster = static_cast<int>(
        std::min<uint32_t>(settings.max_traces_per_cluster(), INT32_MAX));
  }
  if (settings.has_max_clusters()) {
    update.max_clusters = static_cast<int>(
        std::min<uint32_t>(settings.max_clusters(), INT32_MAX));
  }
  if (settings.has_replay_decay())
    update.replay_decay = settings.replay_decay();
  if (settings.forgetting() != v1::FORGETTING_RULE_UNSPECIFIED) {
    update.merge_on_forget = settings.forgetting() == v1::FORGETTING_RULE_MERGE;
  }
  if (settings.has_refresh_pair_radius()) {
    update.refresh_pair_radius = settings.refresh_pair_radius();
  }
  if (settings.has_refresh_uniform()) {
    update.refresh_uniform = settings.refresh_uniform();
  }
  if (settings.has_max_age_seconds()) {
    update.max_age_seconds = static_cast<int64_t>(
        std::min<uint64_t>(settings.max_age_seconds(), INT64_MAX));
  }
  if (settings.has_max_traces_per_robot()) {
    update.max_traces_per_robot = settings.max_traces_per_robot();
  }
  return update;
}

void FleetSettingsToProto(const engine::FleetInfo& info,
                          v1::FleetSettings* out) {
  const core::MemoryOptions& memory = info.settings.memory;
  out->set_code_dimension(info.shape.code_dimension);
  out->set_encoder_version(info.shape.encoder_version);
  out->set_place_unit(info.settings.place_unit);
  out->set_clusters_per_segment(
      static_cast<uint32_t>(memory.clusters_per_batch));
  out->set_max_traces_per_cluster(
      static_cast<uint32_t>(memory.max_traces_per_cluster));
  out->set_max_clusters(static_cast<uint32_t>(memory.max_clusters));
  out->set_replay_decay(memory.replay_decay);
  out->set_forgetting(memory.merge_on_forget ? v1::FORGETTING_RULE_MERGE
                                             : v1::FORGETTING_RULE_DROP);
  out->set_refresh_pair_radius(memory.refresh_pair_radius);
  out->set_refresh_uniform(memory.refresh_uniform);
  out->set_max_age_seconds(static_cast<uint64_t>(
      std::max<int64_t>(0, info.settings.max_age_seconds)));
  out->set_max_traces_per_robot(info.settings.max_traces_per_robot);
  out->set_index(IndexKindToProto(info.settings.index.kind));
  out->set_hnsw_m(static_cast<uint32_t>(info.settings.index.hnsw_m));
  out->set_hnsw_ef_search(
      static_cast<uint32_t>(info.settings.index.hnsw_ef_search));
  switch (info.settings.index.hnsw_codes) {
    case engine::IndexSettings::Codes::kInt8:
      out->set_hnsw_codes(v1::HNSW_CODES_INT8);
      break;
    case engine::IndexSettings::Codes::kFloat:
      out->set_hnsw_codes(v1::HNSW_CODES_FLOAT);
      break;
    case engine::IndexSettings::Codes::kServer:
      break;
  }
}

void DeleteResultToProto(const engine::DeleteResult& result,
                         v1::DeleteTracesResponse* out) {
  out->set_deleted(result.deleted);
  out->set_pending_deleted(result.pending_deleted);
  out->set_clusters_changed(result.clusters_changed);
  out->set_clusters_removed(result.clusters_removed);
  out->set_traces(result.traces);
}

void RewardsResultToProto(const engine::RewardsResult& result,
                          v1::UpdateRewardsResponse* out) {
  out->set_updated(result.updated);
  for (const core::TraceKey& key : result.not_held) {
    KeyToProto(key, out->add_not_held());
  }
}

std::vector<core::TraceKey> KeysFromProto(
    const google::protobuf::RepeatedPtrField<v1::TraceKey>& keys) {
  std::vector<core::TraceKey> out;
  out.reserve(keys.size());
  for (const v1::TraceKey& key : keys) {
    out.push_back(core::TraceKey{key.robot_id(), key.seq()});
  }
  return out;
}

void TraceLookupToProto(const engine::TraceLookup& lookup,
                        v1::GetTracesResponse* out) {
  out->mutable_traces()->Reserve(static_cast<int>(lookup.traces.size()));
  for (const core::MemoryTrace& trace : lookup.traces) {
    TraceToProto(trace, out->add_traces());
  }
  for (const core::TraceKey& key : lookup.missing) {
    KeyToProto(key, out->add_missing());
  }
}

}  // namespace fleetmem::transport
