// K-means with k-means++ seeding (Eq. 14): partitions points into k sets
// minimising the within-cluster sum of squared distances.
#ifndef FLEETMEM_SERVICES_CORE_KMEANS_H_
#define FLEETMEM_SERVICES_CORE_KMEANS_H_

#include <random>
#include <vector>

#include "Eigen/Core"

namespace fleetmem::core {

struct KMeansResult {
  // Cluster of each point (column of the input), in [0, k).
  std::vector<int> assignment;
  // One centroid per column; k columns. Every cluster has >= 1 point.
  Eigen::MatrixXf centroids;
  // Sum of squared distances of the points to their centroids.
  double inertia = 0.0;
  int iterations = 0;
};

// Clusters the columns of `points` into k = min(k, points.cols()) groups.
// Seeds with k-means++ from `rng`, then runs Lloyd iterations until no
// assignment changes or `max_iterations` is reached. An emptied cluster is
// re-seeded with the point farthest from its centroid. Requires k >= 1 and at
// least one point. Deterministic for a given rng state.
KMeansResult KMeans(const Eigen::MatrixXf& points, int k, int max_iterations,
                    std::mt19937_64& rng);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_KMEANS_H_
