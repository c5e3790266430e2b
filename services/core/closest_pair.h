// Closest pair of centroids under insertions and removals (Eqs. 16-17)
// without an O(K^2) scan per removal: every point keeps its nearest neighbour;
// an ordered set of (distance, point) yields the closest pair in O(log K).
// Insert is O(K); Remove is O(K) per point whose neighbour was removed.
#ifndef FLEETMEM_SERVICES_CORE_CLOSEST_PAIR_H_
#define FLEETMEM_SERVICES_CORE_CLOSEST_PAIR_H_

#include <cstdint>
#include <optional>
#include <set>
#include <unordered_map>
#include <utility>

#include "Eigen/Core"

namespace fleetmem::core {

class ClosestPairTracker {
 public:
  struct Pair {
    uint64_t a = 0;  // a < b
    uint64_t b = 0;
    double distance = 0.0;
  };

  // Adds a point; `id` must not be present. All points have one dimension.
  void Insert(uint64_t id, const Eigen::VectorXf& point);
  // Removes a point if present.
  void Remove(uint64_t id);
  // The pair with the smallest Euclidean distance (ties: smallest ids);
  // nullopt with fewer than two points.
  std::optional<Pair> Closest() const;
  size_t size() const { return points_.size(); }

 private:
  struct Entry {
    Eigen::VectorXf point;
    uint64_t neighbour = 0;
    double distance = 0.0;
  };
  void Recompute(uint64_t id, Entry& entry);

  std::unordered_map<uint64_t, Entry> points_;
  std::set<std::pair<double, uint64_t>> by_distance_;  // (distance, id)
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_CLOSEST_PAIR_H_
