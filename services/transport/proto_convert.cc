#include "services/transport/proto_convert.h"

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

}  // namespace fleetmem::transport
