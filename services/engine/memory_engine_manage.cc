// MemoryEngine's calls that manage a fleet and what it holds: CreateFleet,
// UpdateFleet, GetFleet, DeleteTraces, retention, UpdateRewards and
// GetTraces
// (docs/api.md, "Fleets an operator manages").
#include <algorithm>
#include <climits>
#include <cmath>
#include <functional>
#include <map>
#include <optional>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/validation.h"
#include "services/engine/memory_engine_fleet.h"

namespace fleetmem::engine {
namespace {

// One kTracesDeleted event per cluster that lost traces (trace_count: what
// it keeps, 0 for one left empty) and one for the pending traces deleted
// (cluster 0), in cluster order.
std::vector<core::MemoryEvent> DeletionEvents(
    const core::RemovalResult& removal,
    const std::vector<core::MemoryTrace>& pending_removed,
    const core::TraceFilter& filter) {
  std::map<uint64_t, std::vector<core::MemoryTrace>> removed_from;
  for (const core::MemoryTrace& trace : removal.removed) {
    removed_from[trace.cluster_id].push_back(trace);
  }
  std::map<uint64_t, core::MemoryEvent> events;
  for (const core::Cluster& emptied : removal.emptied) {
    core::Cluster before = emptied;
    before.traces = removed_from[emptied.id];
    core::MemoryEvent event =
        core::DescribeCluster(before, core::EventType::kTracesDeleted);
    event.traces_dropped = event.trace_count;
    event.trace_count = 0;
    events[emptied.id] = event;
  }
  for (const core::Cluster& changed : removal.changed) {
    core::MemoryEvent event =
        core::DescribeCluster(changed, core::EventType::kTracesDeleted);
    event.traces_dropped =
        static_cast<uint32_t>(removed_from[changed.id].size());
    events[changed.id] = event;
  }
  std::vector<core::MemoryEvent> out;
  if (!pending_removed.empty()) {
    core::MemoryEvent event;
    event.type = core::EventType::kTracesDeleted;
    event.robot_id = filter.robot_id;
    event.domain = filter.domain;
    event.traces_dropped = static_cast<uint32_t>(pending_removed.size());
    out.push_back(event);
  }
  for (auto& [cluster_id, event] : events) out.push_back(std::move(event));
  return out;
}

}  // namespace

absl::Status MemoryEngine::Fleet::StoreMutation(const FleetMutation& mutation) {
  absl::Status status;
  {
    absl::ReaderMutexLock lock(&mu);
    status = engine->store_->Apply(id, mutation);
  }
  absl::MutexLock lock(&mu);
  if (!status.ok()) {
    Reload().IgnoreError();
    return status;
  }
  if (mutation.put_meta) meta = mutation.meta;
  return absl::OkStatus();
}

void MemoryEngine::Fleet::AdvancePosition(uint64_t log_position,
                                          FleetMutation* mutation) const {
  if (!mutation->put_meta) mutation->meta = meta;
  if (log_position > mutation->meta.log_position) {
    mutation->put_meta = true;
    mutation->meta.log_position = log_position;
  }
  // A log entry's apply: the log is the durable copy (FleetMutation::sync).
  if (log_position != 0) mutation->sync = false;
}

absl::Status MemoryEngine::Fleet::StageDelete(
    const std::function<bool(const core::MemoryTrace&)>& leaves,
    const core::TraceFilter& filter, uint64_t log_position,
    DeleteResult* result, FleetMutation* mutation) {
  std::vector<core::TraceKey> keys;
  for (const auto& [cluster_id, cluster] : memory.clusters()) {
    for (const core::MemoryTrace& trace : cluster.traces) {
      if (leaves(trace)) keys.push_back(trace.key());
    }
  }
  core::RemovalResult removal =
      memory.Remove(keys, [this](const core::MemoryTrace& trace) {
        std::vector<float> code;
        index.CopyCode(trace.key(), &code);  // empty if missing: left out
        return code;
      });
  std::vector<core::MemoryTrace> pending_removed = pending.RemoveIf(leaves);
  result->deleted = removal.removed.size() + pending_removed.size();
  result->pending_deleted = pending_removed.size();
  result->clusters_changed = removal.changed.size();
  result->clusters_removed = removal.emptied.size();
  if (result->deleted == 0) {
    AdvancePosition(log_position, mutation);
    return absl::OkStatus();
  }
  index.MarkChanged();  // forgetting's centroids

  mutation->put_meta = true;
  mutation->meta = meta;
  for (const core::Cluster& emptied : removal.emptied) {
    mutation->erase_clusters.push_back(emptied.id);
  }
  for (const core::MemoryTrace& trace : pending_removed) {
    mutation->erase_pending.push_back(trace.key());
  }
  std::vector<core::TraceKey> leaving = keys;
  for (const core::MemoryTrace& trace : pending_removed) {
    leaving.push_back(trace.key());
  }
  // A changed cluster's traces go without the codes memory dropped: the
  // store keeps the ones it holds (FleetMutation::put_clusters).
  for (core::Cluster& changed : removal.changed) {
    mutation->put_clusters.push_back(std::move(changed));
  }
  if (absl::Status status = index.Remove(leaving); !status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\": a delete could not be staged, reloading: "
                         << status;
    Reload().IgnoreError();
    return absl::InternalError(absl::StrCat(
        "fleet \"", id, "\": nothing deleted: ", status.message()));
  }
  for (core::MemoryEvent& event :
       DeletionEvents(removal, pending_removed, filter)) {
    event.id = mutation->meta.next_event_id++;
    event.timestamp_ns = engine->options_.now_ns();
    mutation->append_events.push_back(std::move(event));
  }
  RetainEvents(engine->options_.max_events_per_fleet, mutation->meta,
               *mutation);
  AdvancePosition(log_position, mutation);
  PublishHeld();
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::StageRewards(
    std::span<const core::RewardUpdate> updates, uint64_t log_position,
    RewardsResult* result, FleetMutation* mutation) {
  // A trace named twice takes its last rewards: each key is set once, at
  // its last update (no rescans of what is staged).
  absl::flat_hash_map<core::TraceKey, size_t> last;
  for (size_t i = 0; i < updates.size(); ++i) last[updates[i].key] = i;
  for (size_t i = 0; i < updates.size(); ++i) {
    const core::RewardUpdate& update = updates[i];
    if (last.at(update.key) != i) continue;
    if (memory.SetReward(update.key, update.reward_external,
                         update.reward_internal)) {
      mutation->update_traces.push_back(*memory.Find(update.key));
      ++result->updated;
    } else if (const core::MemoryTrace* trace =
                   pending.SetReward(update.key, update.reward_external,
                                     update.reward_internal)) {
      mutation->put_pending.push_back(*trace);
      ++result->updated;
    } else {
      result->not_held.push_back(update.key);
    }
  }
  // Without the codes memory dropped: an update keeps the stored code
  // (FleetMutation::update_traces).
  AdvancePosition(log_position, mutation);
  return absl::OkStatus();
}

absl::Status MemoryEngine::CheckDeleteTraces(std::string_view fleet_id,
                                             const core::TraceFilter& filter) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (status.ok()) status = core::ValidateTraceFilter("", filter);
  if (!status.ok()) return status;
  if (filter.selects_all()) {
    return absl::InvalidArgumentError(
        "name a robot_id, a domain, a seq range or a time range: a delete "
        "without one would remove every trace of the fleet");
  }
  return absl::OkStatus();
}

absl::StatusOr<DeleteResult> MemoryEngine::DeleteTraces(
    std::string_view fleet_id, const core::TraceFilter& filter,
    uint64_t log_position) {
  absl::Status status = CheckDeleteTraces(fleet_id, filter);
  if (!status.ok()) return status;
  return Delete(fleet_id, log_position, [&filter](const Fleet&) {
    return Selection{[&filter](const core::MemoryTrace& trace) {
                       return filter.Matches(trace);
                     },
                     filter};
  });
}

absl::StatusOr<DeleteResult> MemoryEngine::EnforceRetention(
    std::string_view fleet_id, int64_t now_ns, uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  absl::StatusOr<DeleteResult> result =
      Delete(fleet_id, log_position, [now_ns](const Fleet& fleet) {
        return Selection{fleet.RetentionLeaves(now_ns), core::TraceFilter{}};
      });
  if (result.ok() && result->deleted > 0 && hooks_.on_retention) {
    hooks_.on_retention(fleet_id, result->deleted);
  }
  return result;
}

std::function<bool(const core::MemoryTrace&)>
MemoryEngine::Fleet::RetentionLeaves(int64_t now_ns) const {
  const FleetSettings settings = Settings();
  std::optional<int64_t> oldest_kept_ns;
  if (settings.max_age_seconds > 0) {
    constexpr int64_t kNs = 1'000'000'000;
    oldest_kept_ns =
        now_ns -
        std::min<int64_t>(settings.max_age_seconds, INT64_MAX / kNs) * kNs;
  }
  // Per robot, the smallest seq kept: the robot's newest
  // max_traces_per_robot of what the fleet holds.
  std::map<std::string, uint64_t, std::less<>> first_kept;
  if (settings.max_traces_per_robot > 0) {
    std::map<std::string, std::vector<uint64_t>, std::less<>> seqs;
    for (const auto& [cluster_id, cluster] : memory.clusters()) {
      for (const core::MemoryTrace& trace : cluster.traces) {
        seqs[trace.robot_id].push_back(trace.seq);
      }
    }
    for (const auto& [robot_id, traces] : pending.by_robot()) {
      for (const core::MemoryTrace& trace : traces) {
        seqs[robot_id].push_back(trace.seq);
      }
    }
    const size_t keep = settings.max_traces_per_robot;
    for (auto& [robot_id, robot_seqs] : seqs) {
      if (robot_seqs.size() <= keep) continue;
      std::nth_element(robot_seqs.begin(), robot_seqs.begin() + (keep - 1),
                       robot_seqs.end(), std::greater<uint64_t>());
      first_kept[robot_id] = robot_seqs[keep - 1];
    }
  }
  return [oldest_kept_ns,
          first_kept = std::move(first_kept)](const core::MemoryTrace& trace) {
    if (oldest_kept_ns && trace.timestamp_ns < *oldest_kept_ns) return true;
    auto bound = first_kept.find(trace.robot_id);
    return bound != first_kept.end() && trace.seq < bound->second;
  };
}

absl::StatusOr<DeleteResult> MemoryEngine::Delete(
    std::string_view fleet_id, uint64_t log_position,
    const std::function<Selection(const Fleet&)>& select) {
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  DeleteResult result;
  uint64_t last_event_id = 0;
  absl::Status status;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    FleetMutation mutation;
    {
      absl::MutexLock lock(&fleet->mu);
      status = fleet->EnsureLoaded();
      if (!status.ok()) return status;
      if (!fleet->exists()) return FleetNotFound(fleet_id);
      if (log_position == 0 || log_position > fleet->meta.log_position) {
        const Selection selection = select(*fleet);
        status = fleet->StageDelete(selection.leaves, selection.filter,
                                    log_position, &result, &mutation);
        if (!status.ok()) return status;
      }
    }
    if (!mutation.empty()) {
      // Readers no longer see the deleted traces while they are erased; a
      // failed write brings them back (the reload) and fails the call.
      status = fleet->StoreMutation(mutation);
      if (!status.ok()) return status;
      if (!mutation.append_events.empty()) {
        last_event_id = mutation.append_events.back().id;
      }
    }
    absl::ReaderMutexLock lock(&fleet->mu);
    result.traces = fleet->memory.trace_count() + fleet->pending.size();
  }
  Fleet::Notify(*this, fleet_id, last_event_id);
  return result;
}

absl::Status MemoryEngine::CheckUpdateRewards(
    std::string_view fleet_id,
    std::span<const core::RewardUpdate> updates) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  if (updates.empty() || updates.size() > options_.max_keys_per_call) {
    return absl::InvalidArgumentError(
        absl::StrCat("updates: ", updates.size(), " given; 1..",
                     options_.max_keys_per_call, " per call"));
  }
  for (size_t i = 0; i < updates.size(); ++i) {
    const core::RewardUpdate& update = updates[i];
    const std::string what = absl::StrCat("updates[", i, "]");
    status =
        core::ValidateId(absl::StrCat(what, ".robot_id"), update.key.robot_id);
    if (!status.ok()) return status;
    const float reward = update.reward_external + update.reward_internal;
    if (!std::isfinite(update.reward_external) ||
        !std::isfinite(update.reward_internal) || !std::isfinite(reward) ||
        reward < 0.0f) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": reward_external ", update.reward_external,
                       " + reward_internal ", update.reward_internal,
                       " must be finite and >= 0 (R = R_ex + R_in, Eq. 13)"));
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<RewardsResult> MemoryEngine::UpdateRewards(
    std::string_view fleet_id, std::span<const core::RewardUpdate> updates,
    uint64_t log_position) {
  absl::Status status = CheckUpdateRewards(fleet_id, updates);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  RewardsResult result;
  absl::MutexLock writer(&fleet->writer_mu);
  FleetMutation mutation;
  {
    absl::MutexLock lock(&fleet->mu);
    status = fleet->EnsureLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    if (log_position != 0 && log_position <= fleet->meta.log_position) {
      return result;  // applied before
    }
    status = fleet->StageRewards(updates, log_position, &result, &mutation);
    if (!status.ok()) return status;
  }
  if (mutation.empty()) return result;
  status = fleet->StoreMutation(mutation);
  if (!status.ok()) return status;
  return result;
}

absl::StatusOr<TraceLookup> MemoryEngine::GetTraces(
    std::string_view fleet_id, std::span<const core::TraceKey> keys) const {
  if (keys.empty() || keys.size() > options_.max_keys_per_call) {
    return absl::InvalidArgumentError(
        absl::StrCat("keys: ", keys.size(), " given; 1..",
                     options_.max_keys_per_call, " per call"));
  }
  for (size_t i = 0; i < keys.size(); ++i) {
    absl::Status status = core::ValidateId(
        absl::StrCat("keys[", i, "].robot_id"), keys[i].robot_id);
    if (!status.ok()) return status;
  }
  return Fleet::ReadExisting(
      *this, fleet_id, [&](const Fleet& fleet) -> absl::StatusOr<TraceLookup> {
        TraceLookup lookup;
        absl::flat_hash_set<core::TraceKey> seen;
        size_t bytes = 0;
        for (const core::TraceKey& key : keys) {
          if (!seen.insert(key).second) continue;
          const core::MemoryTrace* trace = fleet.FindTrace(key);
          if (trace == nullptr) {
            lookup.missing.push_back(key);
            continue;
          }
          bytes +=
              4 * size_t{fleet.meta.code_dimension} + trace->attachment.size();
          if (bytes > options_.max_read_bytes) {
            return absl::InvalidArgumentError(absl::StrCat(
                "keys: the traces found hold more than max_read_bytes ",
                options_.max_read_bytes, " (codes and attachments) by key ",
                lookup.traces.size() + lookup.missing.size(),
                "; ask in parts"));
          }
          lookup.traces.push_back(*trace);
        }
        absl::Status filled = fleet.FillCodes(lookup.traces);
        if (!filled.ok()) return filled;
        return lookup;
      });
}

namespace {

// Retention and the place unit, beside core::ValidateMemoryOptions.
absl::Status ValidateSettings(const FleetSettings& settings) {
  if (absl::Status status = core::ValidateMemoryOptions(settings.memory);
      !status.ok()) {
    return status;
  }
  if (settings.place_unit.size() > 32) {
    return absl::InvalidArgumentError(absl::StrCat("place_unit is ",
                                                   settings.place_unit.size(),
                                                   " characters; at most 32"));
  }
  if (settings.max_age_seconds < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_age_seconds is ", settings.max_age_seconds,
                     "; must be >= 0 (0: no bound)"));
  }
  const IndexSettings& index = settings.index;
  if (index.hnsw_m != 0 && (index.hnsw_m < 2 || index.hnsw_m > 128)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "hnsw_m is ", index.hnsw_m, "; must be 2..128 (0: the server's)"));
  }
  if (index.hnsw_ef_search < 0 || index.hnsw_ef_search > 10'000) {
    return absl::InvalidArgumentError(
        absl::StrCat("hnsw_ef_search is ", index.hnsw_ef_search,
                     "; must be 1..10000 (0: the server's)"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status MemoryEngine::CheckCreateFleet(
    std::string_view fleet_id, const CreateFleetRecord& record) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  if (record.code_dimension == 0 ||
      record.code_dimension > core::kMaxCodeDimension) {
    return absl::InvalidArgumentError(
        absl::StrCat("code_dimension is ", record.code_dimension,
                     "; must be in 1..", core::kMaxCodeDimension));
  }
  if (record.encoder_version.size() > core::kMaxEncoderVersionLength) {
    return absl::InvalidArgumentError(
        absl::StrCat("encoder_version is ", record.encoder_version.size(),
                     " characters; at most ", core::kMaxEncoderVersionLength));
  }
  return ValidateSettings(record.settings);
}

absl::Status MemoryEngine::CreateFleet(std::string_view fleet_id,
                                       const CreateFleetRecord& record,
                                       uint64_t log_position) {
  absl::Status status = CheckCreateFleet(fleet_id, record);
  if (!status.ok()) return status;
  // A log entry's fleet was admitted (max_fleets, the dimension) before
  // it was acknowledged.
  if (log_position == 0) {
    status = quota_->AdmitDimension(fleet_id, record.code_dimension);
    if (!status.ok()) return status;
  }
  absl::StatusOr<Fleet*> added =
      Fleet::FindOrAdd(*this, fleet_id, /*admit=*/log_position == 0);
  if (!added.ok()) return added.status();
  Fleet* fleet = *added;
  absl::MutexLock writer(&fleet->writer_mu);
  FleetMutation mutation;
  std::unique_ptr<PlaceIndex> index;
  {
    absl::ReaderMutexLock lock(&fleet->mu);
    if (fleet->exists()) {
      return absl::FailedPreconditionError(
          absl::StrCat("fleet \"", V(fleet_id), "\" exists already"));
    }
    index = NewIndex(record.code_dimension, record.settings.index);
    if (index == nullptr) {
      return absl::InternalError(absl::StrCat(
          "the index factory made no index for fleet \"", V(fleet_id), "\""));
    }
    mutation.put_meta = true;
    mutation.meta = fleet->meta;
    mutation.meta.code_dimension = record.code_dimension;
    mutation.meta.encoder_version = record.encoder_version;
    mutation.meta.settings = record.settings;
    fleet->AdvancePosition(log_position, &mutation);
    status = store_->Apply(fleet->id, mutation);
  }
  if (!status.ok()) return status;
  absl::MutexLock lock(&fleet->mu);
  fleet->meta = mutation.meta;
  fleet->SetOptions(record.settings.memory);
  fleet->index.Start(std::move(index));
  return absl::OkStatus();
}

absl::StatusOr<uint64_t> MemoryEngine::DeleteFleet(std::string_view fleet_id,
                                                   uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  // Before writer_mu, as SaveIndexSnapshots takes them: no snapshot of the
  // fleet is written behind the delete.
  absl::MutexLock snapshots(&fleet->snapshot_mu);
  absl::MutexLock writer(&fleet->writer_mu);
  FleetMeta kept;
  uint64_t traces = 0;
  {
    absl::ReaderMutexLock lock(&fleet->mu);
    status = fleet->CheckLoaded();
    if (!status.ok()) return status;
    if (log_position != 0 && log_position <= fleet->meta.log_position) {
      return 0;  // applied before
    }
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    traces = fleet->memory.trace_count() + fleet->pending.size();
    kept.log_position = std::max(log_position, fleet->meta.log_position);
    kept.next_event_id = fleet->meta.next_event_id;
    kept.first_event_id = fleet->meta.next_event_id;
    kept.next_cluster_id = fleet->meta.next_cluster_id;
    status = store_->DeleteFleet(fleet->id, kept);
  }
  if (!status.ok()) return status;  // one write: nothing was deleted
  absl::MutexLock lock(&fleet->mu);
  fleet->Reset(kept);
  fleet->PublishHeld();
  FLEETMEM_LOG(kInfo) << "fleet \"" << fleet->id << "\" deleted (" << traces
                      << " traces)";
  return traces;
}

absl::StatusOr<FleetSettings> MemoryEngine::UpdateFleet(
    std::string_view fleet_id, const FleetSettingsUpdate& update,
    uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  absl::MutexLock writer(&fleet->writer_mu);
  FleetMutation mutation;
  FleetSettings settings;
  {
    absl::ReaderMutexLock lock(&fleet->mu);
    status = fleet->CheckLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    settings = fleet->Settings();
    if (log_position != 0 && log_position <= fleet->meta.log_position) {
      return settings;  // applied before
    }
    settings = update.AppliedTo(std::move(settings));
    status = ValidateSettings(settings);
    if (!status.ok()) return status;
    mutation.put_meta = true;
    mutation.meta = fleet->meta;
    mutation.meta.settings = settings;
    fleet->AdvancePosition(log_position, &mutation);
    status = store_->Apply(fleet->id, mutation);
  }
  if (!status.ok()) return status;
  absl::MutexLock lock(&fleet->mu);
  fleet->meta = mutation.meta;
  fleet->SetOptions(settings.memory);
  fleet->index.MarkChanged();
  return settings;
}

absl::StatusOr<FleetInfo> MemoryEngine::GetFleet(
    std::string_view fleet_id) const {
  return Fleet::ReadExisting(
      *this, fleet_id, [](const Fleet& fleet) -> absl::StatusOr<FleetInfo> {
        FleetInfo info;
        info.shape.code_dimension = fleet.meta.code_dimension;
        info.shape.encoder_version = fleet.meta.encoder_version;
        info.settings = fleet.Settings();
        info.own_settings = fleet.meta.settings.has_value();
        return info;
      });
}

}  // namespace fleetmem::engine
