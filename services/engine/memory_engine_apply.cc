#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <functional>
#include <iterator>
#include <map>
#include <random>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#include "services/engine/memory_engine.h"

#if __has_include(<malloc.h>)
#include <malloc.h>
#endif

#include "absl/cleanup/cleanup.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/feature_space.h"
#include "services/core/static_memory.h"
#include "services/core/validation.h"
#include "services/engine/memory_engine_fleet.h"
#include "services/engine/trace_handles.h"

namespace fleetmem::engine {

// Rates refuse by the clock, and the code dimension of a new fleet is
// checked once: only a direct call is admitted here. An entry of a log
// (log_position != 0) was admitted when it was appended (WritePath, or the
// fleet's owner in distributed mode), and applying it again after a
// restart must not be refused.
absl::Status MemoryEngine::Fleet::AdmitDirectCall(
    UploadQuota& quota, std::span<const core::MemoryTrace> traces,
    bool is_new) {
  if (is_new) {
    if (absl::Status status = quota.AdmitDimension(id, traces[0].code.size());
        !status.ok()) {
      return status;
    }
  }
  return quota.AdmitRates(id, traces);
}

// The traces not received before, as pending records in `mutation`, and
// the robots' records with them; duplicates (seqs already received or
// repeated within the upload: inserting into a copy of the robot's SeqSet
// detects both) counted in `result`.
std::map<std::string, RobotRecord> MemoryEngine::Fleet::NewTraces(
    std::span<const core::MemoryTrace> traces, UploadResult* result,
    FleetMutation& mutation) const {
  std::map<std::string, RobotRecord> changed_robots;
  for (const core::MemoryTrace& trace : traces) {
    auto [it, inserted] = changed_robots.try_emplace(trace.robot_id);
    RobotRecord& record = it->second;
    if (inserted) {
      auto known = robots.find(trace.robot_id);
      if (known != robots.end()) {
        record = known->second;
      } else {
        record.robot_id = trace.robot_id;
      }
    }
    if (!record.received.Insert(trace.seq)) {
      ++result->duplicates;
      continue;
    }
    core::MemoryTrace accepted = trace;
    accepted.replay_count = 0;
    accepted.cluster_id = 0;
    mutation.put_pending.push_back(std::move(accepted));
  }
  return changed_robots;
}

// Whether `arriving` fills some robot's segment (its pending traces reach
// segment_size): the upload then consolidates that robot.
bool MemoryEngine::Fleet::FillsSegment(
    std::span<const core::MemoryTrace> arriving) const {
  absl::flat_hash_map<std::string_view, size_t> counts;
  for (const core::MemoryTrace& trace : arriving) ++counts[trace.robot_id];
  for (const auto& [robot_id, count] : counts) {
    if (pending.Of(robot_id).size() + count >= engine->options_.segment_size) {
      return true;
    }
  }
  return false;
}

absl::Status MemoryEngine::Fleet::WriteUpload(
    std::span<const core::MemoryTrace> traces, uint64_t log_position,
    const core::ConsolidationPlan* plan, UploadResult* result,
    Notices* notices) {
  absl::Status status;
  absl::MutexLock writer(&writer_mu);
  {
    absl::MutexLock lock(&mu);
    status = EnsureLoaded();
  }
  PreparedUpload prepared;
  if (status.ok()) {
    absl::ReaderMutexLock lock(&mu);
    status = PrepareUpload(traces, log_position, result, &prepared);
    if (status.ok() && !prepared.mutation.put_pending.empty() &&
        !prepared.fills_segment) {
      status = engine->store_->Apply(id, prepared.mutation);
      prepared.stored = true;
    }
  }
  const size_t added = prepared.mutation.put_pending.size();
  PlaceIndex* place_index = nullptr;
  {
    absl::MutexLock lock(&mu);
    if (status.ok() && added > 0) {
      status = CommitUpload(std::move(prepared), result, notices, plan);
    }
    notices->consolidated.clusters = memory.clusters().size();
    notices->consolidated.traces = memory.trace_count();
    PublishHeld();
    place_index = index.get();
  }
  // The consolidation's store write, beside queries.
  if (status.ok()) {
    status = StoreStaged(notices);
    if (!status.ok()) place_index = nullptr;  // reloaded: a new index
  }
  // The index's back-pressure, outside the fleet's lock: queries go on
  // while the uploader pays for the graph inserts. The index is replaced
  // only under writer_mu, held here.
  if (status.ok() && added > 0 && place_index != nullptr) {
    if (absl::Status caught = place_index->CatchUp(added); !caught.ok()) {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << id << "\": place index catching up: "
          << caught;  // the codes stay searchable in its exact segment
    }
  }
  return status;
}

absl::Status MemoryEngine::Fleet::PrepareUpload(
    std::span<const core::MemoryTrace> traces, uint64_t log_position,
    UploadResult* result, PreparedUpload* prepared) {
  absl::Status status = CheckLoaded();
  if (!status.ok()) return status;
  // An entry at or before the fleet's position is applied already: after a
  // DeleteFleet its traces must not come back.
  if (log_position != 0 && log_position <= meta.log_position) {
    result->duplicates = traces.size();
    return absl::OkStatus();
  }
  const bool is_new = !exists();
  status = ValidateUpload(id, traces, is_new ? nullptr : &meta,
                          engine->options_.max_traces_per_upload,
                          /*check_values=*/log_position == 0);
  if (!status.ok()) return status;
  if (traces.empty()) return absl::OkStatus();
  UploadQuota& quota = *engine->quota_;
  if (log_position == 0) {
    status = AdmitDirectCall(quota, traces, is_new);
    if (!status.ok()) return status;
  }
  FleetMutation& mutation = prepared->mutation;
  std::map<std::string, RobotRecord> changed_robots =
      NewTraces(traces, result, mutation);
  result->accepted = mutation.put_pending.size();
  if (mutation.put_pending.empty()) return absl::OkStatus();
  // The stored-traces limit refuses a direct call; an entry of a log was
  // admitted by it before it was acknowledged (engine/admission.h), and is
  // applied even past a limit lowered since: a log never stalls behind an
  // entry it acknowledged.
  if (log_position == 0) {
    status = quota.AdmitStored(id, memory.trace_count() + pending.size(),
                               mutation.put_pending.size());
    if (!status.ok()) {
      *result = UploadResult{};
      mutation = FleetMutation{};
      return status;
    }
  }
  for (auto& [robot_id, record] : changed_robots) {
    auto known = robots.find(robot_id);
    const uint64_t before =
        known == robots.end() ? 0 : known->second.received.size();
    if (record.received.size() != before) mutation.put_robots.push_back(record);
  }

  prepared->fills_segment = FillsSegment(mutation.put_pending);
  if (is_new) {
    mutation.put_meta = true;
    mutation.meta = meta;
    mutation.meta.code_dimension = static_cast<uint32_t>(traces[0].code.size());
    mutation.meta.encoder_version = traces[0].encoder_version;
    prepared->new_index =
        engine->NewIndex(mutation.meta.code_dimension,
                         mutation.meta.settings ? mutation.meta.settings->index
                                                : IndexSettings());
    if (prepared->new_index == nullptr) {
      mutation = FleetMutation{};
      return absl::InternalError(absl::StrCat(
          "the index factory made no index for fleet \"", id, "\""));
    }
  }
  if (log_position > meta.log_position) {
    if (!mutation.put_meta) mutation.meta = meta;
    mutation.put_meta = true;
    mutation.meta.log_position = log_position;
  }
  // A log entry's apply: the log is the durable copy (FleetMutation::sync).
  if (log_position != 0) mutation.sync = false;
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::CommitUpload(
    PreparedUpload prepared, UploadResult* result, Notices* notices,
    const core::ConsolidationPlan* plan) {
  FleetMutation& mutation = prepared.mutation;
  const bool stored = prepared.stored;
  // Not stored yet: memory runs ahead of the store until the write of the
  // consolidation this upload triggers (StoreStaged), and a failure reloads
  // the fleet.
  CarriedUpload carried;
  if (!stored) {
    carried.mutation.put_meta = mutation.put_meta;
    carried.mutation.meta = mutation.meta;
    carried.mutation.put_robots = mutation.put_robots;
    carried.mutation.sync = mutation.sync;
  }
  if (mutation.put_meta) meta = mutation.meta;
  if (prepared.new_index != nullptr) index.Start(std::move(prepared.new_index));
  for (RobotRecord& record : mutation.put_robots) {
    std::string robot_id = record.robot_id;
    robots[robot_id] = std::move(record);
  }
  std::vector<core::TraceKey> fresh_keys;
  fresh_keys.reserve(mutation.put_pending.size());
  for (core::MemoryTrace& trace : mutation.put_pending) {
    fresh_keys.push_back(trace.key());
    AddPending(std::move(trace));
  }
  // Pending traces are searchable at once (a robot relocalises against what
  // the fleet uploaded a moment ago, not only what is consolidated).
  std::vector<const core::MemoryTrace*> fresh;
  fresh.reserve(fresh_keys.size());
  for (const core::TraceKey& key : fresh_keys) fresh.push_back(FindTrace(key));
  absl::Status status = index.Add(fresh);
  if (!status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\": index update failed, rebuilding: " << status;
    absl::Status reloaded = Reload();
    if (!stored) {
      return absl::InternalError(absl::StrCat(
          "fleet \"", id, "\": index update failed (", status.message(),
          "); nothing of this upload was stored"));
    }
    if (!reloaded.ok()) return reloaded;
  }

  std::vector<std::string> full;
  for (const auto& [robot_id, robot_pending] : pending.by_robot()) {
    if (robot_pending.size() >= engine->options_.segment_size) {
      full.push_back(robot_id);
    }
  }
  if (!stored) {
    const std::string carrier = full.empty() ? std::string() : full.front();
    for (const core::TraceKey& key : fresh_keys) {
      if (key.robot_id == carrier) {
        carried.unstored.insert(key);
      } else {
        carried.mutation.put_pending.push_back(*FindTrace(key));
      }
    }
    if (full.empty()) {
      // PrepareUpload's count and memory disagree; store the upload alone.
      status = engine->store_->Apply(id, carried.mutation);
      if (!status.ok()) {
        Reload().IgnoreError();
        return status;
      }
    }
  }
  for (size_t i = 0; i < full.size(); ++i) {
    status = ConsolidateRobot(full[i], notices,
                              !stored && i == 0 ? &carried : nullptr,
                              i == 0 ? plan : nullptr);
    if (!status.ok()) return status;
    ++result->consolidations;
  }
  return absl::OkStatus();
}

core::ConsolidationPlan MemoryEngine::Fleet::Plan(
    const std::vector<core::MemoryTrace>& batch) const {
  if (batch.empty()) return {};
  std::mt19937_64 segment_rng(
      SegmentSeed(seed, batch.front().robot_id, batch.front().seq));
  // The copy of memory's options: PlanAhead runs without the lock that
  // guards memory.
  return core::PlanConsolidation(PlanOptions(), batch, segment_rng);
}

std::optional<core::ConsolidationPlan> MemoryEngine::Fleet::PlanAhead(
    std::span<const core::MemoryTrace> traces) {
  if (traces.empty()) return std::nullopt;
  const std::string& robot_id = traces.front().robot_id;
  for (const core::MemoryTrace& trace : traces) {
    if (trace.robot_id != robot_id) return std::nullopt;
  }
  std::vector<core::MemoryTrace> segment;
  core::SeqSet received;
  {
    absl::ReaderMutexLock lock(&mu);
    if (!stale.ok() || !exists()) return std::nullopt;
    // Planning runs before PrepareUpload's checks: an upload of another
    // shape (a code of another dimension would overrun the plan's matrix)
    // plans nothing. Its values are PrepareUpload's to check (a plan of a
    // refused upload is dropped).
    if (!ValidateUpload(id, traces, &meta,
                        engine->options_.max_traces_per_upload,
                        /*check_values=*/false)
             .ok()) {
      return std::nullopt;
    }
    auto known = robots.find(robot_id);
    if (known != robots.end()) received = known->second.received;
    const std::span<const core::MemoryTrace> held = pending.Of(robot_id);
    if (held.size() + traces.size() < engine->options_.segment_size) {
      return std::nullopt;
    }
    segment.assign(held.begin(), held.end());
  }
  // As PrepareUpload accepts them (duplicates, also within the upload, out).
  for (const core::MemoryTrace& trace : traces) {
    if (received.Insert(trace.seq)) segment.push_back(trace);
  }
  if (segment.size() < engine->options_.segment_size) return std::nullopt;
  return Plan(segment);
}

namespace {

// What a consolidation changes among the fleet's clusters, for the store:
// the clusters no longer held (forgotten whole, or merged into another),
// sorted, and the held ones that are new or that a merge changed.
struct ClusterChanges {
  std::vector<uint64_t> erased;
  std::vector<uint64_t> put;
};

ClusterChanges ChangesOf(const core::ConsolidationResult& outcome) {
  absl::flat_hash_set<uint64_t> added_ids;
  for (const core::Cluster& cluster : outcome.added) {
    added_ids.insert(cluster.id);
  }
  absl::flat_hash_set<uint64_t> removed_ids;
  for (const core::Cluster& cluster : outcome.forgotten) {
    removed_ids.insert(cluster.id);
  }
  for (const core::ClusterMerge& merge : outcome.merged) {
    removed_ids.insert(merge.from.id);
  }
  ClusterChanges changes;
  // Erasures come first in the store: a merged cluster's moved traces are
  // written again with their survivor.
  for (uint64_t removed : removed_ids) {
    if (!added_ids.contains(removed)) changes.erased.push_back(removed);
  }
  std::sort(changes.erased.begin(), changes.erased.end());
  for (const core::Cluster& cluster : outcome.added) {
    if (!removed_ids.contains(cluster.id)) changes.put.push_back(cluster.id);
  }
  for (uint64_t changed : outcome.changed) {
    if (!added_ids.contains(changed)) changes.put.push_back(changed);
  }
  return changes;
}

// The consolidation's events (clusters added, forgotten, merged) appended
// to `mutation` under `meta`'s next ids at `now_ns`, and the fleet's
// counters; events past `retained` (0: all kept) erased. Returns the
// traces the merges dropped.
size_t AppendConsolidationEvents(const core::ConsolidationResult& outcome,
                                 int64_t now_ns, size_t retained,
                                 FleetMeta& meta, FleetMutation& mutation) {
  auto append_event = [&](core::MemoryEvent event) {
    event.id = meta.next_event_id++;
    event.timestamp_ns = now_ns;
    mutation.append_events.push_back(std::move(event));
  };
  for (const core::Cluster& cluster : outcome.added) {
    append_event(
        core::DescribeCluster(cluster, core::EventType::kClusterAdded));
  }
  for (const core::Cluster& cluster : outcome.forgotten) {
    append_event(
        core::DescribeCluster(cluster, core::EventType::kClusterForgotten));
  }
  size_t merge_dropped = 0;
  for (const core::ClusterMerge& merge : outcome.merged) {
    core::MemoryEvent event =
        core::DescribeCluster(merge.from, core::EventType::kClusterMerged);
    event.merged_into = merge.into;
    event.traces_dropped = static_cast<uint32_t>(merge.dropped.size());
    append_event(std::move(event));
    merge_dropped += merge.dropped.size();
  }
  meta.consolidations += 1;
  meta.clusters_forgotten += outcome.forgotten.size() + outcome.merged.size();
  RetainEvents(retained, meta, mutation);
  return merge_dropped;
}

// The traces that leave the index: the batch was indexed while pending and
// its codes do not change, so only what downsampling dropped, what
// forgetting removed (clusters of this batch included) and what merges
// dropped.
std::vector<core::TraceKey> LeavingTheIndex(
    const core::ConsolidationResult& outcome) {
  std::vector<core::TraceKey> removed;
  for (const core::MemoryTrace& trace : outcome.downsampled) {
    removed.push_back(trace.key());
  }
  for (const core::Cluster& cluster : outcome.forgotten) {
    for (const core::MemoryTrace& trace : cluster.traces) {
      removed.push_back(trace.key());
    }
  }
  for (const core::ClusterMerge& merge : outcome.merged) {
    for (const core::MemoryTrace& trace : merge.dropped) {
      removed.push_back(trace.key());
    }
  }
  return removed;
}

// Whether `plan` (made ahead, without the lock) is the plan of `batch`
// under `options` (an UpdateFleet may have changed them since).
bool PlanFits(const core::ConsolidationPlan* plan,
              const std::vector<core::MemoryTrace>& batch,
              const core::MemoryOptions& options) {
  if (plan == nullptr || plan->keys.size() != batch.size() ||
      !core::PlansAlike(plan->options, options)) {
    return false;
  }
  for (size_t i = 0; i < batch.size(); ++i) {
    if (plan->keys[i] != batch[i].key()) return false;
  }
  return true;
}

}  // namespace

// The store write a consolidation starts from: `carried`'s (the upload that
// filled the segment), and the batch's pending records erased (those of
// the upload itself were never stored).
FleetMutation MemoryEngine::Fleet::ErasingPending(
    const std::vector<core::MemoryTrace>& batch, CarriedUpload* carried) {
  FleetMutation mutation;
  if (carried != nullptr) mutation = std::move(carried->mutation);
  mutation.erase_pending.reserve(batch.size());
  for (const core::MemoryTrace& trace : batch) {
    if (carried != nullptr && carried->unstored.contains(trace.key())) {
      continue;
    }
    mutation.erase_pending.push_back(trace.key());
  }
  return mutation;
}

void MemoryEngine::Fleet::PutClusters(std::span<const uint64_t> cluster_ids,
                                      FleetMutation& mutation,
                                      std::vector<core::TraceKey>* keys) const {
  for (uint64_t cluster_id : cluster_ids) {
    std::optional<core::Cluster> cluster = memory.WithCentroid(cluster_id);
    if (!cluster.has_value()) continue;
    for (const core::MemoryTrace& trace : cluster->traces) {
      keys->push_back(trace.key());
    }
    mutation.put_clusters.push_back(*std::move(cluster));
  }
}

absl::Status MemoryEngine::Fleet::ConsolidateRobot(
    const std::string& robot_id, Notices* notices, CarriedUpload* carried,
    const core::ConsolidationPlan* plan) {
  if (pending.Of(robot_id).empty()) return absl::OkStatus();
  const absl::Time start = absl::Now();
  std::vector<core::MemoryTrace> batch = pending.Take(robot_id);
  FleetMutation mutation = ErasingPending(batch, carried);
  const size_t batch_size = batch.size();
  // The meta as the consolidations staged before this one leave it.
  const FleetMeta& base =
      notices->staged.empty() ? meta : notices->staged.back().meta;
  const uint64_t first_cluster_id = base.next_cluster_id;
  const bool fits = PlanFits(plan, batch, memory.options());
  std::optional<core::ConsolidationPlan> own;
  if (!fits) own = Plan(batch);
  core::ConsolidationResult outcome = memory.Consolidate(
      std::move(batch), first_cluster_id, fits ? *plan : *own);
  index.MarkChanged();  // forgetting's centroids

  FleetMeta new_meta = base;
  new_meta.next_cluster_id = first_cluster_id + outcome.added.size();
  for (const core::Cluster& cluster : outcome.added) {
    new_meta.next_cluster_id =
        std::max(new_meta.next_cluster_id, cluster.id + 1);
  }
  ClusterChanges changes = ChangesOf(outcome);
  mutation.erase_clusters.insert(mutation.erase_clusters.end(),
                                 changes.erased.begin(), changes.erased.end());
  std::sort(mutation.erase_clusters.begin(), mutation.erase_clusters.end());
  // The mutation holds copies of the batch's codes (the only ones memory
  // still has), and the index may drop its own below.
  std::vector<core::TraceKey> kept;
  PutClusters(changes.put, mutation, &kept);
  const size_t merge_dropped = AppendConsolidationEvents(
      outcome, engine->options_.now_ns(), engine->options_.max_events_per_fleet,
      new_meta, mutation);
  mutation.put_meta = true;
  mutation.meta = new_meta;

  if (absl::Status status = index.Remove(LeavingTheIndex(outcome));
      !status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\": index update failed, rebuilding: " << status;
    notices->staged.clear();
    Reload().IgnoreError();
    return absl::InternalError(absl::StrCat(
        "fleet \"", id, "\": index update failed (", status.message(),
        "); the consolidation of robot \"", robot_id, "\" was not stored"));
  }
  ReleaseCodes(kept);
  notices->staged.push_back(
      StagedConsolidation{std::move(mutation), std::move(new_meta)});

  ConsolidateResult batch_result;
  batch_result.consolidated_traces = batch_size;
  batch_result.downsampled_traces = outcome.downsampled.size() + merge_dropped;
  batch_result.clusters_added = outcome.added.size();
  batch_result.clusters_forgotten =
      outcome.forgotten.size() + outcome.merged.size();
  Accumulate(batch_result, &notices->consolidated);
  ++notices->consolidations;
  notices->consolidation_seconds += absl::ToDoubleSeconds(absl::Now() - start);
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::StoreStaged(Notices* notices) {
  if (notices->staged.empty()) return absl::OkStatus();
  absl::Status status;
  size_t stored = 0;
  {
    absl::ReaderMutexLock lock(&mu);
    for (const StagedConsolidation& staged : notices->staged) {
      status = engine->store_->Apply(id, staged.mutation);
      if (!status.ok()) break;
      ++stored;
    }
  }
  absl::MutexLock lock(&mu);
  if (!status.ok()) {
    // Memory and the index ran ahead of the store: back to what it holds.
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\": " << notices->staged.size() - stored << " of "
                         << notices->staged.size()
                         << " consolidations not stored: " << status;
    notices->staged.clear();
    notices->consolidations = 0;
    notices->consolidated = ConsolidateResult{};
    Reload().IgnoreError();
    return status;
  }
  meta = notices->staged.back().meta;
  for (const StagedConsolidation& staged : notices->staged) {
    const std::vector<core::MemoryEvent>& events =
        staged.mutation.append_events;
    if (!events.empty()) notices->last_event_id = events.back().id;
  }
  notices->staged.clear();
  return absl::OkStatus();
}

absl::StatusOr<std::vector<core::MemoryTrace>> MemoryEngine::Fleet::DrawSample(
    std::string_view robot_id, size_t count, std::string_view request_id,
    uint64_t log_position, const core::ReadFilter* filter,
    FleetMutation* mutation) {
  RobotRecord record;
  auto known = robots.find(robot_id);
  if (known != robots.end()) {
    record = known->second;
  } else {
    record.robot_id = std::string(robot_id);
  }
  if (!request_id.empty() && request_id == record.last_sample_request_id) {
    // A retry: the same traces again, as they are now, counted once.
    std::vector<core::MemoryTrace> again;
    for (const core::TraceKey& key : record.last_sample) {
      const core::MemoryTrace* trace = FindTrace(key);
      if (trace != nullptr && trace->cluster_id != 0) again.push_back(*trace);
    }
    absl::Status status = FillCodes(again);
    if (!status.ok()) return status;
    return again;
  }
  std::vector<core::MemoryTrace> traces;
  if (filter != nullptr) {
    // Among the matching traces: the sum tree holds every trace's weight,
    // so a filtered draw reads them all (in memory order, which replicas
    // share), seeded as below for a logged call.
    std::mt19937_64 logged_rng(SegmentSeed(seed, "log", log_position));
    traces = memory.SampleForReplayInMemoryOrder(
        count, log_position == 0 ? rng : logged_rng,
        [filter](const core::MemoryTrace& trace) {
          return filter->Matches(trace);
        });
  } else if (log_position == 0) {
    traces = memory.SampleForReplay(count, rng);
  } else {
    // Seeded by the entry. In memory order: the same draw on every replica
    // that applies the entry, whatever order its sampler's slots are in (a
    // restored or restarted replica's differs from one that applied the
    // log all along).
    std::mt19937_64 logged_rng(SegmentSeed(seed, "log", log_position));
    traces = engine->options_.draw_in_memory_order
                 ? memory.SampleForReplayInMemoryOrder(count, logged_rng)
                 : memory.SampleForReplay(count, logged_rng);
  }
  if (traces.empty()) return traces;
  // The store's update of their replay counts, copied before the codes
  // come back: an update keeps the stored code (FleetMutation::
  // update_traces), so the copies need none (1 MB less a draw of 1,000).
  std::vector<core::MemoryTrace> counted = traces;
  if (absl::Status status = FillCodes(traces); !status.ok()) {
    Reload().IgnoreError();  // drops the incremented counts
    return status;
  }
  record.replayed += traces.size();
  if (!request_id.empty()) {
    record.last_sample_request_id = std::string(request_id);
    record.last_sample.clear();
    for (const core::MemoryTrace& trace : traces) {
      record.last_sample.push_back(trace.key());
    }
  }
  mutation->update_traces = std::move(counted);
  mutation->update_traces_held = true;  // drawn from the static memory
  mutation->put_robots.push_back(std::move(record));
  if (log_position > meta.log_position) {
    mutation->put_meta = true;
    mutation->meta = meta;
    mutation->meta.log_position = log_position;
  }
  return traces;
}

void MemoryEngine::Fleet::FinishSample(FleetMutation mutation) {
  if (mutation.put_meta) meta = std::move(mutation.meta);
  for (RobotRecord& record : mutation.put_robots) {
    std::string robot_id = record.robot_id;
    robots[robot_id] = std::move(record);
  }
}

}  // namespace fleetmem::engine
