// Closest pair of centroids under insertions and removals (Eqs. 16-17)
// without an O(K^2) scan per removal: every point keeps its nearest neighbour
// (and knows which points keep it as theirs); an ordered set of
// (distance, point) yields the closest pair in O(log K).
//
// Below ClosestPairOptions::exact_below points the neighbours are found by
// exact scans: Insert is O(K); Remove is O(K) per point whose neighbour was
// removed; the pair is the exact closest pair. From exact_below points on
// they are found through an HNSW graph over the points (hnswlib): Insert and
// Remove cost O(log K) distance computations each, and the pair is the
// closest pair up to the graph's recall (a point whose nearest neighbour the
// new point becomes is only updated if it is among the new point's
// `reverse_candidates` approximate nearest neighbours). bench/forgetting_bench
// measures both against each other; docs/performance.md gives the agreement.
#ifndef FLEETMEM_SERVICES_CORE_CLOSEST_PAIR_H_
#define FLEETMEM_SERVICES_CORE_CLOSEST_PAIR_H_

#include <cstdint>
#include <memory>
#include <optional>
#include <set>
#include <span>
#include <unordered_map>
#include <utility>
#include <vector>

#include "Eigen/Core"
#include "absl/status/status.h"
#include "services/core/byte_stream.h"
#include "services/core/hnsw_graph.h"

namespace fleetmem::core {

struct ClosestPairOptions {
  // Exact scans below this many points; the HNSW graph from it on (the
  // graph is dropped again below exact_below / 2). The default keeps every
  // memory up to 2,048 clusters exact (the paper's K_max is 100), where one
  // scan of 259-d centroids costs well under a millisecond.
  size_t exact_below = 2048;
  // The HNSW graph (links per node, candidate lists, seed).
  HnswGraphOptions graph;
  // Approximate neighbours of a new point checked for points whose nearest
  // neighbour it becomes.
  size_t reverse_candidates = 32;
};

class ClosestPairTracker {
 public:
  struct Pair {
    uint64_t a = 0;  // a < b
    uint64_t b = 0;
    double distance = 0.0;
  };

  explicit ClosestPairTracker(ClosestPairOptions options = {});
  ~ClosestPairTracker();
  ClosestPairTracker(const ClosestPairTracker& other);
  ClosestPairTracker& operator=(const ClosestPairTracker& other);
  ClosestPairTracker(ClosestPairTracker&&) noexcept;
  ClosestPairTracker& operator=(ClosestPairTracker&&) noexcept;

  // Adds a point; `id` must not be present. All points have one dimension.
  void Insert(uint64_t id, const Eigen::VectorXf& point);
  // Removes a point if present.
  void Remove(uint64_t id);
  // The pair with the smallest Euclidean distance (ties: smallest ids);
  // nullopt with fewer than two points.
  std::optional<Pair> Closest() const;
  size_t size() const { return points_.size(); }
  // True while neighbours are found through the HNSW graph.
  bool approximate() const { return graph_ != nullptr; }
  // The point of `id` (valid until the next change), or an empty span.
  std::span<const float> point(uint64_t id) const;
  // The ids of every point, ascending.
  std::vector<uint64_t> ids() const;

  // Writes every point with its neighbour bookkeeping, and the graph, for
  // Load: a restart that skips rebuilding them (100,000 centroids take
  // seconds to insert).
  void Save(ByteWriter& out) const;
  // Restores what Save wrote into this empty tracker, whose options must be
  // those of the saved one: the same pair, the same later answers.
  // DATA_LOSS when the bytes are malformed or inconsistent (every
  // neighbour, keeper and graph slot is checked); the tracker is then
  // empty. RESOURCE_EXHAUSTED when out of memory.
  absl::Status Load(ByteReader& in);

 private:
  struct Graph;  // hnswlib, kept out of this header
  using PointView = Eigen::Map<const Eigen::VectorXf>;
  struct Entry {
    // The point while there is no graph; empty while the graph holds it
    // (one copy of each centroid: 259-d points cost about 1 KB each).
    Eigen::VectorXf point;
    uint64_t neighbour = 0;
    double distance = 0.0;
    bool has_neighbour = false;
    // Points whose neighbour this one is.
    std::vector<uint64_t> keepers;
    uint32_t slot = 0;  // label in the graph
  };
  // Makes `neighbour` (at `distance`) the neighbour of `id`.
  void SetNeighbour(uint64_t id, Entry& entry, uint64_t neighbour,
                    double distance);
  void ClearNeighbour(uint64_t id, Entry& entry);
  // Finds the neighbour of `id` again (exact scan or graph search).
  void Recompute(uint64_t id, Entry& entry);
  // Candidate neighbours of `point` among the other points: all of them, or
  // the graph's `count` approximate nearest.
  std::vector<uint64_t> Candidates(PointView point, size_t count) const;
  // The entry's point, in the entry or in the graph.
  PointView PointOf(const Entry& entry) const;
  // Builds the graph from the entries' points, which it then holds.
  void BuildGraph();
  // Moves the points back into the entries and drops the graph.
  void DropGraph();
  // Adds the entry's point to the graph, which then holds it.
  void AddToGraph(uint64_t id, Entry& entry);
  // Load without its clean-up on failure.
  absl::Status LoadOrThrow(ByteReader& in);

  ClosestPairOptions options_;
  std::unordered_map<uint64_t, Entry> points_;
  std::set<std::pair<double, uint64_t>> by_distance_;  // (distance, id)
  std::unique_ptr<Graph> graph_;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_CLOSEST_PAIR_H_
