// The static memory M_S of one fleet: bounded clusters of memory traces,
// consolidated from batches (Algorithm 1), pruned by forgetting (Algorithm 2)
// and sampled for replay (Eq. 18). Pure and single-threaded: the caller locks,
// persists what each call reports, and injects randomness.
#ifndef FLEETMEM_SERVICES_CORE_STATIC_MEMORY_H_
#define FLEETMEM_SERVICES_CORE_STATIC_MEMORY_H_

#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <random>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "services/core/byte_stream.h"
#include "services/core/closest_pair.h"
#include "services/core/importance_sampler.h"
#include "services/core/memory_options.h"
#include "services/core/robot_numbers.h"
#include "services/core/types.h"

namespace fleetmem::core {

// One merge of forgetting (MemoryOptions::merge_on_forget): cluster `from`
// is no longer held; `into`, which is, holds the traces of both that the
// merge's downsampling kept.
struct ClusterMerge {
  Cluster from;  // as it was before the merge, with its centroid
  uint64_t into = 0;
  // Traces of either cluster that the merge's downsampling dropped
  // (DownsampleAlongPlaces), cluster_id 0.
  std::vector<MemoryTrace> dropped;
};

// What one consolidation changed; the caller persists it.
struct ConsolidationResult {
  // Clusters appended to the memory (after downsampling), oldest first.
  // Clusters that forgetting removed again in the same call are in
  // `forgotten` too.
  std::vector<Cluster> added;
  // Traces dropped by downsampling (Eq. 15).
  std::vector<MemoryTrace> downsampled;
  // Clusters removed by forgetting (Algorithm 2) with their traces, in
  // removal order (merge_on_forget false).
  std::vector<Cluster> forgotten;
  // Merges of forgetting, in order (merge_on_forget true). No `from` id is
  // held afterwards; an `into` may itself be merged away by a later merge.
  std::vector<ClusterMerge> merged;
  // Ids of the clusters held after the call whose traces or centroid a
  // merge changed (each once, ascending); added clusters may be among them.
  std::vector<uint64_t> changed;
};

// What one removal of traces changed (StaticMemory::Remove); the caller
// persists it.
struct RemovalResult {
  // The traces removed, as they were held (a dropped code stays empty).
  std::vector<MemoryTrace> removed;
  // Held clusters that lost traces but not all, as they are now, each with
  // its centroid recomputed from the traces it keeps; ascending by id.
  std::vector<Cluster> changed;
  // Clusters that lost every trace: no longer held. As they were before,
  // with their centroids, without traces (they are in `removed`);
  // ascending by id.
  std::vector<Cluster> emptied;
};

// The code of a held trace whose code the memory dropped (DropCode): the
// caller keeps the codes elsewhere.
using CodeOf = std::function<std::vector<float>(const MemoryTrace& trace)>;

// The part of Algorithm 1 that depends on the batch alone (feature-spatial
// codes, k-means, downsampling, the kept traces' centroids): pure, so a
// caller may compute it without holding the memory's lock and hand it to
// Consolidate.
struct ConsolidationPlan {
  // Per new cluster, the positions in the batch of the traces it keeps.
  std::vector<std::vector<size_t>> kept;
  // Positions of the traces downsampling dropped (Eq. 15).
  std::vector<size_t> dropped;
  // Per new cluster, the mean feature-spatial code of its kept traces.
  std::vector<std::vector<float>> centroids;
  // The batch's trace keys, in order: the plan fits only this batch.
  std::vector<TraceKey> keys;
  // The options it was planned under (K, N_max, ...): it fits a memory
  // whose options plan alike (PlansAlike).
  MemoryOptions options;
};

// Plans the consolidation of `batch` (one robot's segment) under `options`:
// k-means++ into min(K, |batch|) clusters with randomness from `rng`, then
// downsampling of each to N_max traces by reward; with clustering off, one
// cluster of the whole batch. An empty batch gives an empty plan.
ConsolidationPlan PlanConsolidation(const MemoryOptions& options,
                                    const std::vector<MemoryTrace>& batch,
                                    std::mt19937_64& rng);

// True if `a` and `b` plan a batch alike (the options PlanConsolidation
// reads: K, N_max, the spatial scale, clustering, k-means iterations).
bool PlansAlike(const MemoryOptions& a, const MemoryOptions& b);

// Runs `first` and `second` to completion, in either order or at once
// (they touch disjoint state): a caller's way to lend a second thread.
using RunBoth = std::function<void(const std::function<void()>& first,
                                   const std::function<void()>& second)>;

class StaticMemory {
 public:
  // `options` must pass ValidateMemoryOptions.
  explicit StaticMemory(MemoryOptions options);

  StaticMemory(const StaticMemory&) = delete;
  StaticMemory& operator=(const StaticMemory&) = delete;
  StaticMemory(StaticMemory&&) = default;
  StaticMemory& operator=(StaticMemory&&) = default;

  // Puts back a cluster loaded from storage as is (no forgetting). Its id
  // must be new.
  void Restore(Cluster cluster);
  // Restore of each of `clusters` into this empty memory, with forgetting's
  // centroid bookkeeping loaded from what SaveCentroids wrote instead of
  // rebuilt (at 100,000 clusters that saves seconds), then reconciled with
  // `clusters`: the bookkeeping may come from an earlier state of the
  // memory (a periodic snapshot before a crash), so centroids of clusters
  // no longer held are removed and those of clusters it lacks, or holds
  // with another centroid, are inserted (`*reconciled`, if given, counts
  // them). OK when the snapshot was used; otherwise (malformed, or of
  // another dimension) the bookkeeping is rebuilt as Restore does and the
  // status says why. The memory is complete either way. The clusters'
  // traces do not move.
  //
  // Into an empty memory, with distinct ids ascending (a memory image's
  // order), the restore is two halves that touch disjoint state: the
  // location of every trace by key (the smaller: 3.4 % of a start's
  // samples at 1,000,000 traces, docs/performance.md) and the rest
  // (clusters, the sampler's slots and weights, the counts, forgetting's
  // centroids). `run_both`, if given, runs them: on two
  // threads, or one after the other (the core starts no thread). Otherwise,
  // or for any other memory, one thread restores it all.
  absl::Status RestoreAll(std::vector<Cluster> clusters, ByteReader& centroids,
                          size_t* reconciled = nullptr,
                          const RunBoth& run_both = nullptr);
  // Writes forgetting's centroid bookkeeping for RestoreAll.
  void SaveCentroids(ByteWriter& out) const { centroids_.Save(out); }

  // Algorithm 1 on one batch (one robot's segment): builds feature-spatial
  // codes, clusters them with k-means++ into min(K, |batch|) clusters,
  // downsamples each to N_max traces by reward, appends the clusters with ids
  // first_cluster_id, first_cluster_id + 1, ..., then forgets while more than
  // K_max clusters are held. With clustering off the batch becomes one
  // cluster as is. An empty batch changes nothing. All codes of the batch
  // must have one dimension (the caller validates with ValidateTrace).
  ConsolidationResult Consolidate(std::vector<MemoryTrace> batch,
                                  uint64_t first_cluster_id,
                                  std::mt19937_64& rng);
  // The same with the plan already made by PlanConsolidation for exactly
  // this batch (plan.keys are the batch's keys, in order; the caller
  // checks).
  ConsolidationResult Consolidate(std::vector<MemoryTrace> batch,
                                  uint64_t first_cluster_id,
                                  const ConsolidationPlan& plan);

  // Refresh (Eq. 18): draws up to `count` distinct traces with weight
  // gamma^n * R, increments their replay_count and returns copies of them
  // (with the new counts), in draw order. O(count log trace_count()): the
  // weights live in a sum tree kept up to date by every change. With
  // options().refresh_pair_radius above 0, the pair-keeping draw instead,
  // and with refresh_uniform weights of 1 (both O(trace_count() log
  // trace_count()): pair_draw.h).
  std::vector<MemoryTrace> SampleForReplay(size_t count, std::mt19937_64& rng);
  // The same draw over the traces in an order that depends only on what
  // memory holds (clusters by id, each cluster's traces in order), not on
  // the history of the sampler's slots: memories that hold the same traces
  // draw the same ones from equal generators, however each was built (one
  // consolidated live, another restored). Distributed mode draws this way.
  // O(trace_count() log count) (SampleWithoutReplacement).
  // With `accept`, only the traces it accepts are drawn (a filtered
  // replay), with the same weights.
  std::vector<MemoryTrace> SampleForReplayInMemoryOrder(
      size_t count, std::mt19937_64& rng,
      const std::function<bool(const MemoryTrace&)>& accept = nullptr);

  // Removes the held traces among `keys` (the others are passed over): a
  // cluster that keeps some of its traces gets its centroid recomputed as
  // the mean feature-spatial code of those it keeps (`code_of` gives the
  // codes the memory dropped; a trace whose code it cannot give, an empty
  // one, is left out of the mean), so that nothing removed weighs on
  // forgetting any more; a cluster left empty is no longer held. The
  // replay sampler and the per-robot and per-domain counts follow.
  RemovalResult Remove(std::span<const TraceKey> keys, const CodeOf& code_of);

  // Sets the rewards of the held trace `key`: R_ex, R_in and R = R_ex +
  // R_in (Eq. 13), its replay weight gamma^n * R (Eq. 18) following. The
  // caller validates them (finite, R >= 0). False if the trace is not held.
  bool SetReward(const TraceKey& key, float reward_external,
                 float reward_internal);

  // The trace with this key, or nullptr. Valid until the next mutation.
  const MemoryTrace* Find(const TraceKey& key) const;

  // Frees the code of the trace with `key` (false if there is none), for a
  // caller that keeps the codes elsewhere (the engine's place index): the
  // memory's algorithms read the codes of the batch they consolidate, never
  // those of the traces they hold. Find, clusters() and SampleForReplay
  // then show the trace with an empty code.
  bool DropCode(const TraceKey& key);

  // Clusters by id (ascending = oldest first). Their `centroid` is empty:
  // forgetting's tracker holds each centroid, once; WithCentroid gives a
  // cluster whole.
  const std::map<uint64_t, Cluster>& clusters() const { return clusters_; }
  // A copy of the held cluster `id` with its centroid (the store's record),
  // or nullopt.
  std::optional<Cluster> WithCentroid(uint64_t id) const;
  // The held cluster `id`'s centroid (empty if none is held), valid until
  // the memory changes.
  std::span<const float> CentroidOf(uint64_t id) const {
    return centroids_.point(id);
  }
  size_t trace_count() const { return trace_count_; }
  // Traces held per robot and per domain (kept up to date by every change,
  // so statistics cost O(robots + domains), not O(traces)).
  const std::map<std::string, uint64_t, std::less<>>& traces_by_robot() const {
    return traces_by_robot_;
  }
  const std::map<std::string, uint64_t, std::less<>>& traces_by_domain() const {
    return traces_by_domain_;
  }
  const MemoryOptions& options() const { return options_; }
  // Takes new options (a fleet's UpdateFleet): every later consolidation,
  // forgetting and draw uses them; the replay weights of the traces held
  // follow a new gamma or reward floor now (O(traces)). Forgetting's
  // tracker keeps its own (forgetting_exact_below, seed). `options` must
  // pass ValidateMemoryOptions.
  void SetOptions(const MemoryOptions& options);

 private:
  // How Insert adds a cluster.
  struct InsertMode {
    // Its centroid into forgetting's tracker (false: RestoreAll loaded
    // the tracker).
    bool with_centroid = true;
    // An empty memory's restore (slots taken in order): the traces'
    // replay weights are appended here for WeightedSampler::SetAll
    // instead of set one by one.
    std::vector<double>* weights = nullptr;
    // Its traces into location_ (false: RestoreAll's other half does it,
    // LocateInOrder).
    bool with_locations = true;
  };
  // Adds the cluster and its traces.
  void Insert(Cluster cluster, const InsertMode& mode);
  void Insert(Cluster cluster) { Insert(std::move(cluster), InsertMode()); }
  // Forgetting's tracker from `centroids` (what SaveCentroids wrote),
  // reconciled with `clusters` (RestoreAll); `*changes` counts what it
  // changed. Not OK: the tracker is left as it was.
  absl::Status RestoreCentroids(std::vector<Cluster>& clusters,
                                ByteReader& centroids, size_t* changes);
  // The locations of the traces of `clusters` (id, traces) when they take
  // slots 0, 1, ... in order: the half of an empty memory's RestoreAll
  // that touches location_ and robots_ alone.
  void LocateInOrder(
      std::span<const std::pair<uint64_t, std::span<const MemoryTrace>>>
          clusters,
      size_t trace_count);
  Cluster Erase(uint64_t cluster_id);
  // Algorithm 2: removes or merges clusters until at most K_max remain.
  void Forget(ConsolidationResult& result);
  // Merges cluster `from` into `into` (both held): see ClusterMerge.
  ClusterMerge Merge(uint64_t from, uint64_t into);
  // A trace's weight in the refresh draw: gamma^n * R (Eq. 18), or 1 with
  // options().refresh_uniform.
  double RefreshWeight(const MemoryTrace& trace) const;

  // Where a trace is: its cluster and its slot in the replay sampler.
  struct Location {
    uint64_t cluster_id = 0;
    uint32_t slot = 0;
  };

  MemoryOptions options_;
  std::map<uint64_t, Cluster> clusters_;
  // Keyed by (robot number, seq): each robot id once, in robots_.
  RobotNumbers robots_;
  absl::flat_hash_map<PackedTraceKey, Location> location_;
  ClosestPairTracker centroids_;
  size_t trace_count_ = 0;
  // Replay weights by slot; slot_trace_[slot] is the trace (nodes of
  // clusters_ do not move, nor do their traces once inserted). Freed slots
  // are reused last-in first-out.
  WeightedSampler replay_;
  std::vector<MemoryTrace*> slot_trace_;
  std::vector<uint32_t> free_slots_;
  std::map<std::string, uint64_t, std::less<>> traces_by_robot_;
  std::map<std::string, uint64_t, std::less<>> traces_by_domain_;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_STATIC_MEMORY_H_
