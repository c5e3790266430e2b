// Robot-side code arithmetic: cosine similarity, the server's code distance
// (Euclidean between L2-normalised codes), exact k-nearest search by brute
// force (the demo's unbounded baseline), distances between places and the
// first-correct rank of a retrieval (relocalisation scoring).
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_CODE_SEARCH_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_CODE_SEARCH_H_

#include <cstddef>
#include <span>
#include <vector>

#include "services/core/feature_space.h"
#include "services/core/types.h"

namespace fleetmem::robot {

// cos(a, b) for codes of equal size; 1 if both are all zero (the same code),
// 0 if only one is.
float CosineSimilarity(std::span<const float> a, std::span<const float> b);

// The server's code distance (normalised Euclidean), shared with the core.
using core::CodeDistance;

// Exact nearest codes by CodeDistance over a fixed set. Not thread-safe for
// Add; Search is const and may run concurrently.
class BruteForceIndex {
 public:
  explicit BruteForceIndex(size_t dimension) : dimension_(dimension) {}

  // Appends `code` (of the index's dimension) with a caller-chosen label.
  void Add(std::span<const float> code, double label);
  size_t size() const { return labels_.size(); }

  // Labels of the min(k, size()) nearest codes to `query`, nearest first
  // (ties by insertion order).
  std::vector<double> Search(std::span<const float> query, size_t k) const;
  // The same, with each one's CodeDistance to `query`.
  struct Neighbour {
    double label = 0.0;
    float distance = 0.0f;
  };
  std::vector<Neighbour> SearchScored(std::span<const float> query,
                                      size_t k) const;

 private:
  size_t dimension_;
  std::vector<float> normalised_;  // size() rows of dimension_
  std::vector<double> labels_;
};

// Euclidean distance between two places (x, y, z; yaw ignored).
double PlaceDistance(const core::Place& a, const core::Place& b);

// 1-based rank of the first of `retrieved` (nearest first) within
// `tolerance` of `query` (PlaceDistance), or 0 if none is.
int FirstCorrectRank(std::span<const core::Place> retrieved,
                     const core::Place& query, double tolerance);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_CODE_SEARCH_H_
