#include "services/core/kmeans.h"

#include <algorithm>
#include <cassert>
#include <cstdint>
#include <limits>

namespace fleetmem::core {
namespace {

using MatrixXd = Eigen::MatrixXd;
using VectorXd = Eigen::VectorXd;

// Uniform in [0, 1) from the top 53 bits: the same on every standard library
// (std::uniform_real_distribution is implementation-defined).
double Uniform01(std::mt19937_64& rng) {
  return static_cast<double>(rng() >> 11) * 0x1.0p-53;
}

// Squared Euclidean distances, points (d x n) against centres (d x k):
// n x k, |x|^2 + |c|^2 - 2 x.c clamped at 0.
MatrixXd SquaredDistances(const MatrixXd& points, const VectorXd& point_norms,
                          const MatrixXd& centres) {
  const VectorXd centre_norms = centres.colwise().squaredNorm().transpose();
  MatrixXd d = -2.0 * (points.transpose() * centres);
  d.colwise() += point_norms;
  d.rowwise() += centre_norms.transpose();
  return d.cwiseMax(0.0);
}

// k-means++ seeding: the first centre uniformly, each next one with
// probability proportional to its squared distance to the nearest centre.
MatrixXd SeedPlusPlus(const MatrixXd& points, const VectorXd& point_norms,
                      int k, std::mt19937_64& rng) {
  const Eigen::Index n = points.cols();
  MatrixXd centres(points.rows(), k);
  std::vector<bool> chosen(n, false);
  Eigen::Index first = static_cast<Eigen::Index>(Uniform01(rng) * n);
  first = std::min(first, n - 1);
  centres.col(0) = points.col(first);
  chosen[first] = true;
  VectorXd nearest =
      SquaredDistances(points, point_norms, centres.col(0)).col(0);
  for (int c = 1; c < k; ++c) {
    for (Eigen::Index i = 0; i < n; ++i) {
      if (chosen[i]) nearest[i] = 0.0;
    }
    const double total = nearest.sum();
    Eigen::Index pick = -1;
    if (total > 0.0) {
      const double target = Uniform01(rng) * total;
      double cumulative = 0.0;
      for (Eigen::Index i = 0; i < n; ++i) {
        if (nearest[i] <= 0.0) continue;
        cumulative += nearest[i];
        pick = i;  // last positive candidate absorbs rounding at the end
        if (cumulative > target) break;
      }
    } else {
      // Every remaining point coincides with a centre: pick uniformly among
      // the points not chosen yet (k <= n guarantees one exists).
      std::vector<Eigen::Index> free;
      for (Eigen::Index i = 0; i < n; ++i) {
        if (!chosen[i]) free.push_back(i);
      }
      size_t j = static_cast<size_t>(Uniform01(rng) * free.size());
      pick = free[std::min(j, free.size() - 1)];
    }
    centres.col(c) = points.col(pick);
    chosen[pick] = true;
    nearest = nearest.cwiseMin(
        SquaredDistances(points, point_norms, centres.col(c)).col(0));
  }
  return centres;
}

// Nearest centre of every point; a point stays in its current cluster when
// that one is as near as the best (so duplicate points converge), otherwise
// ties go to the smallest index.
void Assign(const MatrixXd& distances, std::vector<int>& assignment) {
  for (Eigen::Index i = 0; i < distances.rows(); ++i) {
    Eigen::Index best = 0;
    const double best_distance = distances.row(i).minCoeff(&best);
    const int current = assignment[i];
    if (current >= 0 && distances(i, current) <= best_distance) continue;
    assignment[i] = static_cast<int>(best);
  }
}

// Gives every empty cluster the point farthest from its own centroid, taken
// from a cluster that keeps at least one point.
void FillEmptyClusters(const MatrixXd& points, const MatrixXd& centres,
                       std::vector<int>& assignment) {
  const int k = static_cast<int>(centres.cols());
  std::vector<int> counts(k, 0);
  for (int a : assignment) ++counts[a];
  for (int c = 0; c < k; ++c) {
    if (counts[c] > 0) continue;
    Eigen::Index farthest = -1;
    double farthest_distance = -1.0;
    for (Eigen::Index i = 0; i < points.cols(); ++i) {
      if (counts[assignment[i]] < 2) continue;
      const double d =
          (points.col(i) - centres.col(assignment[i])).squaredNorm();
      // The first candidate is taken even if its distance is not a number,
      // so an empty cluster is always filled (k <= n).
      if (farthest < 0 || d > farthest_distance) {
        farthest_distance = d;
        farthest = i;
      }
    }
    assert(farthest >= 0);  // k <= n
    if (farthest < 0) return;
    --counts[assignment[farthest]];
    assignment[farthest] = c;
    counts[c] = 1;
  }
}

MatrixXd Means(const MatrixXd& points, const std::vector<int>& assignment,
               int k) {
  MatrixXd sums = MatrixXd::Zero(points.rows(), k);
  VectorXd counts = VectorXd::Zero(k);
  for (Eigen::Index i = 0; i < points.cols(); ++i) {
    sums.col(assignment[i]) += points.col(i);
    counts[assignment[i]] += 1.0;
  }
  for (int c = 0; c < k; ++c) {
    if (counts[c] > 0.0) sums.col(c) /= counts[c];
  }
  return sums;
}

}  // namespace

KMeansResult KMeans(const Eigen::MatrixXf& points_f, int k, int max_iterations,
                    std::mt19937_64& rng) {
  assert(k >= 1 && points_f.cols() >= 1);
  KMeansResult result;
  const Eigen::Index n = points_f.cols();
  if (n == 0 || k < 1) return result;
  k = static_cast<int>(std::min<Eigen::Index>(k, n));

  // Double precision keeps |x|^2 + |c|^2 - 2 x.c accurate.
  const MatrixXd points = points_f.cast<double>();
  const VectorXd point_norms = points.colwise().squaredNorm().transpose();

  MatrixXd centres = SeedPlusPlus(points, point_norms, k, rng);
  std::vector<int> assignment(n, -1);
  Assign(SquaredDistances(points, point_norms, centres), assignment);

  for (int iteration = 0; iteration < max_iterations; ++iteration) {
    FillEmptyClusters(points, centres, assignment);
    centres = Means(points, assignment, k);
    const std::vector<int> previous = assignment;
    Assign(SquaredDistances(points, point_norms, centres), assignment);
    result.iterations = iteration + 1;
    if (assignment == previous) break;
  }
  FillEmptyClusters(points, centres, assignment);
  centres = Means(points, assignment, k);

  double inertia = 0.0;
  for (Eigen::Index i = 0; i < n; ++i) {
    inertia += (points.col(i) - centres.col(assignment[i])).squaredNorm();
  }
  result.assignment = std::move(assignment);
  result.centroids = centres.cast<float>();
  result.inertia = inertia;
  return result;
}

}  // namespace fleetmem::core
