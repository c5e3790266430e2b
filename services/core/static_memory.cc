#include "services/core/static_memory.h"

#include <algorithm>
#include <cassert>
#include <limits>
#include <numeric>
#include <set>
#include <string_view>
#include <utility>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "services/core/downsampler.h"
#include "services/core/feature_space.h"
#include "services/core/importance_sampler.h"
#include "services/core/kmeans.h"
#include "services/core/pair_draw.h"

namespace fleetmem::core {
namespace {

// `sum` / `count` in float (a centroid summed in double).
std::vector<float> Mean(const Eigen::VectorXd& sum, size_t count) {
  std::vector<float> mean(static_cast<size_t>(sum.size()));
  if (count == 0) return mean;
  for (Eigen::Index i = 0; i < sum.size(); ++i) {
    mean[static_cast<size_t>(i)] =
        static_cast<float>(sum[i] / static_cast<double>(count));
  }
  return mean;
}

// Mean feature-spatial code of `traces` (non-empty, equal code sizes).
std::vector<float> Centroid(const std::vector<MemoryTrace>& traces,
                            double spatial_scale_m) {
  Eigen::VectorXd sum;
  for (const MemoryTrace& trace : traces) {
    const Eigen::VectorXd c =
        FeatureSpatialCode(trace, spatial_scale_m).cast<double>();
    if (sum.size() == 0) {
      sum = c;
    } else {
      sum += c;
    }
  }
  return Mean(sum, traces.size());
}

Eigen::VectorXf ToVector(const std::vector<float>& values) {
  return Eigen::Map<const Eigen::VectorXf>(
      values.data(), static_cast<Eigen::Index>(values.size()));
}

}  // namespace

namespace {

ClosestPairOptions ClosestPairOptionsFor(const MemoryOptions& options) {
  ClosestPairOptions closest;
  closest.exact_below =
      static_cast<size_t>(std::max(options.forgetting_exact_below, 2));
  closest.graph.seed = options.seed;
  return closest;
}

}  // namespace

bool PlansAlike(const MemoryOptions& a, const MemoryOptions& b) {
  return a.clusters_per_batch == b.clusters_per_batch &&
         a.max_traces_per_cluster == b.max_traces_per_cluster &&
         a.spatial_scale_m == b.spatial_scale_m &&
         a.clustering == b.clustering &&
         a.kmeans_max_iterations == b.kmeans_max_iterations;
}

StaticMemory::StaticMemory(MemoryOptions options)
    : options_(std::move(options)),
      centroids_(ClosestPairOptionsFor(options_)) {}

void StaticMemory::Restore(Cluster cluster) {
  if (cluster.centroid.empty() && !cluster.traces.empty()) {
    cluster.centroid = Centroid(cluster.traces, options_.spatial_scale_m);
  }
  if (clusters_.contains(cluster.id)) Erase(cluster.id);  // id must be new
  Insert(std::move(cluster));
}

ConsolidationPlan PlanConsolidation(const MemoryOptions& options,
                                    const std::vector<MemoryTrace>& batch,
                                    std::mt19937_64& rng) {
  ConsolidationPlan plan;
  plan.options = options;
  if (batch.empty()) return plan;
  plan.keys.reserve(batch.size());
  for (const MemoryTrace& trace : batch) plan.keys.push_back(trace.key());
  const Eigen::Index n = static_cast<Eigen::Index>(batch.size());
  Eigen::MatrixXf points(
      static_cast<Eigen::Index>(batch.front().code.size() + 3), n);
  for (Eigen::Index i = 0; i < n; ++i) {
    points.col(i) = FeatureSpatialCode(batch[static_cast<size_t>(i)],
                                       options.spatial_scale_m);
  }
  if (!options.clustering) {
    plan.kept.emplace_back(batch.size());
    std::iota(plan.kept.back().begin(), plan.kept.back().end(), size_t{0});
  } else {
    const int k = static_cast<int>(std::min<size_t>(
        static_cast<size_t>(options.clusters_per_batch), batch.size()));
    const KMeansResult kmeans =
        KMeans(points, k, options.kmeans_max_iterations, rng);
    std::vector<std::vector<size_t>> groups(
        static_cast<size_t>(kmeans.centroids.cols()));
    for (size_t i = 0; i < batch.size(); ++i) {
      groups[static_cast<size_t>(kmeans.assignment[i])].push_back(i);
    }
    for (std::vector<size_t>& group : groups) {
      std::vector<size_t> dropped =
          DownsampleByReward(batch, group, options.max_traces_per_cluster);
      plan.dropped.insert(plan.dropped.end(), dropped.begin(), dropped.end());
      plan.kept.push_back(std::move(group));
    }
  }
  for (const std::vector<size_t>& kept : plan.kept) {
    // Mean feature-spatial code of the kept traces, summed in double.
    Eigen::VectorXd sum = Eigen::VectorXd::Zero(points.rows());
    for (size_t i : kept) {
      sum += points.col(static_cast<Eigen::Index>(i)).cast<double>();
    }
    plan.centroids.push_back(Mean(sum, kept.size()));
  }
  return plan;
}

ConsolidationResult StaticMemory::Consolidate(std::vector<MemoryTrace> batch,
                                              uint64_t first_cluster_id,
                                              std::mt19937_64& rng) {
  const ConsolidationPlan plan = PlanConsolidation(options_, batch, rng);
  return Consolidate(std::move(batch), first_cluster_id, plan);
}

ConsolidationResult StaticMemory::Consolidate(std::vector<MemoryTrace> batch,
                                              uint64_t first_cluster_id,
                                              const ConsolidationPlan& plan) {
  ConsolidationResult result;
  if (batch.empty()) return result;
  assert(plan.keys.size() == batch.size());
  const std::string robot_id = batch.front().robot_id;
  for (size_t i : plan.dropped) {
    batch[i].cluster_id = 0;
    result.downsampled.push_back(std::move(batch[i]));
  }
  for (size_t c = 0; c < plan.kept.size(); ++c) {
    Cluster cluster;
    cluster.id = first_cluster_id + c;
    cluster.robot_id = robot_id;
    cluster.centroid = plan.centroids[c];
    cluster.traces.reserve(plan.kept[c].size());
    for (size_t i : plan.kept[c]) {
      cluster.traces.push_back(std::move(batch[i]));
      cluster.traces.back().cluster_id = cluster.id;
    }
    result.added.push_back(cluster);
    Insert(std::move(cluster));
  }
  Forget(result);
  return result;
}

double StaticMemory::RefreshWeight(const MemoryTrace& trace) const {
  if (options_.refresh_uniform) return 1.0;
  return ReplayWeight(trace.reward, trace.replay_count, options_.replay_decay,
                      options_.reward_floor);
}

std::vector<MemoryTrace> StaticMemory::SampleForReplay(size_t count,
                                                       std::mt19937_64& rng) {
  std::vector<size_t> drawn;
  if (options_.refresh_pair_radius > 0.0 || options_.refresh_uniform) {
    // These draws see every trace (O(n log n), pair_draw.h).
    std::vector<const MemoryTrace*> traces;
    std::vector<double> weights;
    std::vector<size_t> slots;
    for (size_t slot = 0; slot < slot_trace_.size(); ++slot) {
      const MemoryTrace* trace = slot_trace_[slot];
      if (trace == nullptr) continue;
      traces.push_back(trace);
      weights.push_back(RefreshWeight(*trace));
      slots.push_back(slot);
    }
    for (size_t i :
         DrawPairs(traces, weights, count, options_.refresh_pair_radius, rng)) {
      drawn.push_back(slots[i]);
    }
  } else {
    drawn = replay_.Draw(count, rng);
  }
  std::vector<MemoryTrace> out;
  out.reserve(drawn.size());
  for (size_t slot : drawn) {
    MemoryTrace& trace = *slot_trace_[slot];
    if (trace.replay_count < std::numeric_limits<uint32_t>::max()) {
      ++trace.replay_count;
    }
    replay_.Set(slot,
                ReplayWeight(trace.reward, trace.replay_count,
                             options_.replay_decay, options_.reward_floor));
    out.push_back(trace);
  }
  return out;
}

std::vector<MemoryTrace> StaticMemory::SampleForReplayInMemoryOrder(
    size_t count, std::mt19937_64& rng,
    const std::function<bool(const MemoryTrace&)>& accept) {
  std::vector<MemoryTrace*> order;
  std::vector<double> weights;
  order.reserve(trace_count_);
  weights.reserve(trace_count_);
  for (auto& [id, cluster] : clusters_) {
    for (MemoryTrace& trace : cluster.traces) {
      if (accept && !accept(trace)) continue;
      order.push_back(&trace);
      weights.push_back(RefreshWeight(trace));
    }
  }
  std::vector<MemoryTrace> out;
  const std::vector<size_t> drawn =
      options_.refresh_pair_radius > 0.0
          ? DrawPairs(
                std::vector<const MemoryTrace*>(order.begin(), order.end()),
                weights, count, options_.refresh_pair_radius, rng)
          : SampleWithoutReplacement(weights, count, rng);
  out.reserve(drawn.size());
  for (size_t index : drawn) {
    MemoryTrace& trace = *order[index];
    if (trace.replay_count < std::numeric_limits<uint32_t>::max()) {
      ++trace.replay_count;
    }
    const std::optional<PackedTraceKey> packed =
        robots_.Find(trace.robot_id, trace.seq);
    replay_.Set(location_.at(*packed).slot,
                ReplayWeight(trace.reward, trace.replay_count,
                             options_.replay_decay, options_.reward_floor));
    out.push_back(trace);
  }
  return out;
}

const MemoryTrace* StaticMemory::Find(const TraceKey& key) const {
  const std::optional<PackedTraceKey> packed =
      robots_.Find(key.robot_id, key.seq);
  if (!packed.has_value()) return nullptr;
  auto found = location_.find(*packed);
  if (found == location_.end()) return nullptr;
  return slot_trace_[found->second.slot];
}

void StaticMemory::SetOptions(const MemoryOptions& options) {
  const bool reweigh = options.replay_decay != options_.replay_decay ||
                       options.reward_floor != options_.reward_floor;
  options_ = options;
  if (!reweigh) return;
  for (uint32_t slot = 0; slot < slot_trace_.size(); ++slot) {
    const MemoryTrace* trace = slot_trace_[slot];
    if (trace == nullptr) continue;
    replay_.Set(slot,
                ReplayWeight(trace->reward, trace->replay_count,
                             options_.replay_decay, options_.reward_floor));
  }
}

RemovalResult StaticMemory::Remove(std::span<const TraceKey> keys,
                                   const CodeOf& code_of) {
  // The held traces among `keys`, by cluster.
  std::map<uint64_t, absl::flat_hash_set<PackedTraceKey>> leaving;
  for (const TraceKey& key : keys) {
    const std::optional<PackedTraceKey> packed =
        robots_.Find(key.robot_id, key.seq);
    if (!packed.has_value()) continue;
    auto found = location_.find(*packed);
    if (found == location_.end()) continue;
    leaving[found->second.cluster_id].insert(*packed);
  }
  RemovalResult result;
  for (const auto& [cluster_id, packed_keys] : leaving) {
    Cluster cluster = Erase(cluster_id);
    std::vector<MemoryTrace> kept;
    kept.reserve(cluster.traces.size());
    for (MemoryTrace& trace : cluster.traces) {
      const bool leaves =
          packed_keys.contains(*robots_.Find(trace.robot_id, trace.seq));
      (leaves ? result.removed : kept).push_back(std::move(trace));
    }
    if (kept.empty()) {
      cluster.traces.clear();
      result.emptied.push_back(std::move(cluster));
      continue;
    }
    // The centroid of what the cluster keeps, from every kept code (one
    // that neither the memory nor code_of has is left out; none: the
    // centroid stays).
    Eigen::VectorXd sum;
    size_t summed = 0;
    for (const MemoryTrace& trace : kept) {
      MemoryTrace probe;
      const MemoryTrace* with_code = &trace;
      if (trace.code.empty()) {
        probe.code = code_of(trace);
        probe.place = trace.place;
        with_code = &probe;
      }
      if (with_code->code.size() + 3 !=
          static_cast<size_t>(cluster.centroid.size())) {
        continue;
      }
      const Eigen::VectorXd c =
          FeatureSpatialCode(*with_code, options_.spatial_scale_m)
              .cast<double>();
      if (sum.size() == 0) {
        sum = c;
      } else {
        sum += c;
      }
      ++summed;
    }
    if (summed > 0) cluster.centroid = Mean(sum, summed);
    cluster.traces = std::move(kept);
    Insert(std::move(cluster));
    // The copy handed back holds no codes the memory dropped either.
    result.changed.push_back(*WithCentroid(cluster_id));
  }
  return result;
}

bool StaticMemory::SetReward(const TraceKey& key, float reward_external,
                             float reward_internal) {
  const std::optional<PackedTraceKey> packed =
      robots_.Find(key.robot_id, key.seq);
  if (!packed.has_value()) return false;
  auto found = location_.find(*packed);
  if (found == location_.end()) return false;
  MemoryTrace& trace = *slot_trace_[found->second.slot];
  trace.reward_external = reward_external;
  trace.reward_internal = reward_internal;
  trace.reward = reward_external + reward_internal;
  replay_.Set(found->second.slot,
              ReplayWeight(trace.reward, trace.replay_count,
                           options_.replay_decay, options_.reward_floor));
  return true;
}

bool StaticMemory::DropCode(const TraceKey& key) {
  const std::optional<PackedTraceKey> packed =
      robots_.Find(key.robot_id, key.seq);
  if (!packed.has_value()) return false;
  auto found = location_.find(*packed);
  if (found == location_.end()) return false;
  std::vector<float>().swap(slot_trace_[found->second.slot]->code);
  return true;
}

namespace {

void Count(std::map<std::string, uint64_t, std::less<>>& counts,
           const std::string& key, int64_t delta) {
  auto [it, inserted] = counts.try_emplace(key, 0);
  it->second += static_cast<uint64_t>(delta);
  if (it->second == 0) counts.erase(it);
}

// Adds one to `counts` per key given, a lookup per run of equal keys
// (the keys must outlive it).
class RunCounter {
 public:
  explicit RunCounter(std::map<std::string, uint64_t, std::less<>>& counts)
      : counts_(counts) {}
  RunCounter(const RunCounter&) = delete;
  RunCounter& operator=(const RunCounter&) = delete;
  ~RunCounter() { Flush(); }
  void Add(const std::string& key) {
    if (key_ != nullptr && *key_ == key) {
      ++run_;
      return;
    }
    Flush();
    key_ = &key;
    run_ = 1;
  }

 private:
  void Flush() {
    if (key_ != nullptr) Count(counts_, *key_, run_);
  }
  std::map<std::string, uint64_t, std::less<>>& counts_;
  const std::string* key_ = nullptr;
  int64_t run_ = 0;
};

}  // namespace

absl::Status StaticMemory::RestoreCentroids(std::vector<Cluster>& clusters,
                                            ByteReader& centroids,
                                            size_t* changes) {
  for (Cluster& cluster : clusters) {
    if (cluster.centroid.empty() && !cluster.traces.empty()) {
      cluster.centroid = Centroid(cluster.traces, options_.spatial_scale_m);
    }
  }
  ClosestPairTracker loaded(ClosestPairOptionsFor(options_));
  if (!clusters_.empty()) {
    return absl::FailedPreconditionError("RestoreAll into a used memory");
  }
  if (absl::Status status = loaded.Load(centroids); !status.ok()) {
    return status;
  }
  // Every centroid of one memory has one dimension; a point of another
  // means the bytes are not this memory's.
  for (const Cluster& cluster : clusters) {
    const std::span<const float> point = loaded.point(cluster.id);
    if (!point.empty() && point.size() != cluster.centroid.size()) {
      return absl::DataLossError(absl::StrCat(
          "the centroid snapshot holds cluster ", cluster.id, " with ",
          point.size(), " dimensions, the memory ", cluster.centroid.size()));
    }
  }
  absl::flat_hash_set<uint64_t> held;
  held.reserve(clusters.size());
  for (const Cluster& cluster : clusters) held.insert(cluster.id);
  for (uint64_t id : loaded.ids()) {
    if (held.contains(id)) continue;
    loaded.Remove(id);
    ++*changes;
  }
  for (const Cluster& cluster : clusters) {
    const std::span<const float> point = loaded.point(cluster.id);
    if (!point.empty() &&
        std::equal(cluster.centroid.begin(), cluster.centroid.end(),
                   point.begin(), point.end())) {
      continue;
    }
    if (!point.empty()) loaded.Remove(cluster.id);
    loaded.Insert(cluster.id, ToVector(cluster.centroid));
    ++*changes;
  }
  centroids_ = std::move(loaded);
  return absl::OkStatus();
}

void StaticMemory::LocateInOrder(
    std::span<const std::pair<uint64_t, std::span<const MemoryTrace>>> clusters,
    size_t trace_count) {
  location_.reserve(location_.size() + trace_count);  // no rehash on the way
  RunPacker packer(robots_);
  uint32_t slot = 0;
  for (const auto& [cluster_id, traces] : clusters) {
    for (const MemoryTrace& trace : traces) {
      location_[packer.Pack(trace.robot_id, trace.seq)] =
          Location{cluster_id, slot++};
    }
  }
}

absl::Status StaticMemory::RestoreAll(std::vector<Cluster> clusters,
                                      ByteReader& centroids, size_t* reconciled,
                                      const RunBoth& run_both) {
  size_t traces = 0;
  for (const Cluster& cluster : clusters) traces += cluster.traces.size();
  // Into an empty memory the traces take slots 0, 1, ... in order, and the
  // sampler's sums are built once at the end.
  const bool fresh = clusters_.empty() && slot_trace_.empty();
  // Distinct ids (ascending): no cluster replaces another, so the
  // locations follow from the order alone.
  const bool ascending =
      std::adjacent_find(clusters.begin(), clusters.end(),
                         [](const Cluster& a, const Cluster& b) {
                           return a.id >= b.id;
                         }) == clusters.end();
  const bool halves = fresh && ascending && run_both != nullptr;
  // Where each cluster's traces lie, taken before the clusters move into
  // clusters_ (a vector's elements stay where they are when it moves).
  std::vector<std::pair<uint64_t, std::span<const MemoryTrace>>> placed;
  if (halves) {
    placed.reserve(clusters.size());
    for (const Cluster& cluster : clusters) {
      placed.emplace_back(cluster.id, cluster.traces);
    }
  }
  size_t changes = 0;
  absl::Status status;
  auto restore_the_rest = [&] {
    status = RestoreCentroids(clusters, centroids, &changes);
    if (!halves) location_.reserve(location_.size() + traces);
    slot_trace_.reserve(slot_trace_.size() + traces);
    std::vector<double> weights;
    if (fresh) weights.reserve(traces);
    const InsertMode mode{.with_centroid = !status.ok(),
                          .weights = fresh ? &weights : nullptr,
                          .with_locations = !halves};
    for (Cluster& cluster : clusters) {
      if (clusters_.contains(cluster.id)) Erase(cluster.id);  // id must be new
      Insert(std::move(cluster), mode);
    }
    if (fresh) replay_.SetAll(weights);
  };
  if (halves) {
    run_both(restore_the_rest, [&] { LocateInOrder(placed, traces); });
  } else {
    restore_the_rest();
  }
  if (reconciled != nullptr) *reconciled = changes;
  return status;
}

void StaticMemory::Insert(Cluster cluster, const InsertMode& mode) {
  const uint64_t id = cluster.id;
  if (mode.with_centroid) centroids_.Insert(id, ToVector(cluster.centroid));
  // The tracker holds the centroid; one copy (WithCentroid).
  cluster.centroid = std::vector<float>();
  Cluster& stored = clusters_.emplace(id, std::move(cluster)).first->second;
  trace_count_ += stored.traces.size();
  // Counted per run of one robot and of one domain (a cluster's traces
  // are mostly one robot's segment): a map lookup per run, not per trace.
  RunCounter by_robot(traces_by_robot_);
  RunCounter by_domain(traces_by_domain_);
  RunPacker packer(robots_);
  for (MemoryTrace& trace : stored.traces) {
    uint32_t slot;
    if (!free_slots_.empty()) {
      slot = free_slots_.back();
      free_slots_.pop_back();
    } else {
      slot = static_cast<uint32_t>(slot_trace_.size());
      slot_trace_.push_back(nullptr);
    }
    slot_trace_[slot] = &trace;
    const double weight =
        ReplayWeight(trace.reward, trace.replay_count, options_.replay_decay,
                     options_.reward_floor);
    if (mode.weights != nullptr) {
      mode.weights->push_back(weight);  // slot == weights->size() - 1
    } else {
      replay_.Set(slot, weight);
    }
    if (mode.with_locations) {
      location_[packer.Pack(trace.robot_id, trace.seq)] = Location{id, slot};
    }
    by_robot.Add(trace.robot_id);
    by_domain.Add(trace.domain);
  }
}

Cluster StaticMemory::Erase(uint64_t cluster_id) {
  auto node = clusters_.extract(cluster_id);
  if (node.empty()) return Cluster{};
  Cluster cluster = std::move(node.mapped());
  const std::span<const float> centroid = centroids_.point(cluster_id);
  cluster.centroid.assign(centroid.begin(), centroid.end());
  trace_count_ -= cluster.traces.size();
  for (const MemoryTrace& trace : cluster.traces) {
    const std::optional<PackedTraceKey> packed =
        robots_.Find(trace.robot_id, trace.seq);
    auto it = packed.has_value() ? location_.find(*packed) : location_.end();
    if (it != location_.end() && it->second.cluster_id == cluster_id) {
      replay_.Clear(it->second.slot);
      slot_trace_[it->second.slot] = nullptr;
      free_slots_.push_back(it->second.slot);
      location_.erase(it);
    }
    Count(traces_by_robot_, trace.robot_id, -1);
    Count(traces_by_domain_, trace.domain, -1);
  }
  centroids_.Remove(cluster_id);
  return cluster;
}

std::optional<Cluster> StaticMemory::WithCentroid(uint64_t id) const {
  auto it = clusters_.find(id);
  if (it == clusters_.end()) return std::nullopt;
  Cluster whole = it->second;
  const std::span<const float> centroid = centroids_.point(id);
  whole.centroid.assign(centroid.begin(), centroid.end());
  return whole;
}

void StaticMemory::Forget(ConsolidationResult& result) {
  const size_t max_clusters =
      static_cast<size_t>(std::max(options_.max_clusters, 1));
  std::set<uint64_t> changed;
  while (clusters_.size() > max_clusters) {
    const std::optional<ClosestPairTracker::Pair> pair = centroids_.Closest();
    if (!pair) break;
    const double reward_a = clusters_.at(pair->a).MeanReward();
    const double reward_b = clusters_.at(pair->b).MeanReward();
    // Keep what is hard: the lower mean reward goes; ties: the older
    // (smaller id, pair->a).
    const uint64_t victim = reward_b < reward_a ? pair->b : pair->a;
    const uint64_t survivor = victim == pair->a ? pair->b : pair->a;
    if (!options_.merge_on_forget) {
      result.forgotten.push_back(Erase(victim));
      continue;
    }
    result.merged.push_back(Merge(victim, survivor));
    changed.erase(victim);
    changed.insert(survivor);
  }
  result.changed.assign(changed.begin(), changed.end());
}

ClusterMerge StaticMemory::Merge(uint64_t from, uint64_t into) {
  ClusterMerge merge;
  merge.into = into;
  merge.from = Erase(from);
  Cluster survivor = Erase(into);
  // The centroid of the union, from the two centroids weighted by their
  // traces (the codes themselves may be with the caller's index only).
  const size_t n_into = survivor.traces.size();
  const size_t n_from = merge.from.traces.size();
  const double total =
      static_cast<double>(std::max<size_t>(n_into + n_from, 1));
  for (size_t d = 0; d < survivor.centroid.size(); ++d) {
    survivor.centroid[d] = static_cast<float>(
        (static_cast<double>(survivor.centroid[d]) * n_into +
         static_cast<double>(merge.from.centroid[d]) * n_from) /
        total);
  }
  for (const MemoryTrace& trace : merge.from.traces) {
    survivor.traces.push_back(trace);
    survivor.traces.back().cluster_id = into;
  }
  merge.dropped =
      DownsampleAlongPlaces(survivor.traces, options_.max_traces_per_cluster);
  for (MemoryTrace& trace : merge.dropped) trace.cluster_id = 0;
  Insert(std::move(survivor));
  return merge;
}

}  // namespace fleetmem::core
