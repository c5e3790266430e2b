// Parameters of the static memory (BioSLAM Sec. V, memory.md). Defaults are
// the paper's experiment where it gives them, otherwise memory.md's decisions.
#ifndef FLEETMEM_SERVICES_CORE_MEMORY_OPTIONS_H_
#define FLEETMEM_SERVICES_CORE_MEMORY_OPTIONS_H_

#include <cstdint>

#include "absl/status/status.h"

namespace fleetmem::core {

struct MemoryOptions {
  // K: clusters per consolidated batch (Eq. 14); min(K, batch size) is used.
  int clusters_per_batch = 20;
  // N_max: traces kept per cluster by downsampling (Eq. 15).
  int max_traces_per_cluster = 50;
  // K_max: clusters in the static memory before forgetting (Algorithm 2).
  int max_clusters = 100;
  // gamma in w_k = gamma^{n_k} * R_k (Eq. 18); 1 disables time decay.
  double replay_decay = 0.9;
  // Rewards are clamped below to this floor so no trace has zero weight.
  double reward_floor = 1e-3;
  // lambda = 1 / spatial_scale_m in c_k = [z_k, lambda * p_k]: this many
  // metres weigh like one unit of (normalised) code distance.
  double spatial_scale_m = 10.0;
  // Ablation "w/o consolidation-clustering": store every trace of a batch in
  // one cluster, no k-means and no downsampling.
  bool clustering = true;
  // How forgetting (Algorithm 2) removes one cluster of the closest pair.
  // true (memory.md's revised decision): the survivor takes the other's
  // traces, downsampled along the places to N_max when they do not fit
  // (DownsampleAlongPlaces), so the bound K_max limits clusters, not places:
  // a stretch's summer and winter clusters, each other's closest pair, end
  // up as one cluster holding both seasons. false: the paper's Algorithm 2,
  // the other cluster goes with all its traces.
  bool merge_on_forget = true;
  // Lloyd iterations of k-means after k-means++ seeding.
  int kmeans_max_iterations = 50;
  // Seed of the random generators (runs are reproducible). The engine
  // mixes it with the fleet id for replay draws, and with the fleet id, the
  // robot id and the segment's first seq for each segment's k-means++.
  uint64_t seed = 42;
  // Forgetting's closest pair of centroids is found by exact scans while
  // fewer clusters than this are held, and through an HNSW graph over the
  // centroids from then on (ClosestPairTracker; approximate, O(log K) per
  // change instead of O(K)). The paper's memory (K_max = 100) stays exact.
  int forgetting_exact_below = 2048;
  // The refresh draw (Eq. 18, StaticMemory::SampleForReplay). 0: the
  // paper's, successive sampling by gamma^n * R. Above 0: the pair-keeping
  // refresh (pair_draw.h, issue 47): each trace drawn by gamma^n * R comes
  // with the nearest not-yet-drawn trace of another domain within this
  // many place units, so that a robot's dynamic memory holds the places
  // the fleet saw in two domains as pairs.
  double refresh_pair_radius = 0.0;
  // The refresh draws every trace with weight 1 instead of gamma^n * R
  // (uniform replay from the fleet's memory; with refresh_pair_radius, the
  // pairs' anchors uniformly). Issue 47 measured it: docs/results.md.
  bool refresh_uniform = false;
};

// OK if every field is in range; otherwise INVALID_ARGUMENT naming the field.
absl::Status ValidateMemoryOptions(const MemoryOptions& options);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_MEMORY_OPTIONS_H_
