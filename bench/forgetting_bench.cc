// Forgetting (Algorithm 2, Eqs. 16-17): one step of a full static memory —
// find the closest pair of centroids, remove one, add the centroid of a new
// cluster — with fleetmem's ClosestPairTracker against the paper's method as
// written (a kept distance matrix whose minimum is searched on every removal,
// O(K^2) per step), measured in the same run at K_max = 100 (the paper's),
// 1,000 and 5,000 clusters. Centroids are feature-spatial codes of dimension
// 256 + 3 drawn from gaussian blobs.
//
//   build/bin/fleetmem_forgetting_bench --benchmark_min_time=0.2
#include <benchmark/benchmark.h>

#include <cstdint>
#include <limits>
#include <random>
#include <utility>
#include <vector>

#include "Eigen/Core"
#include "bench/bench_main.h"
#include "services/core/closest_pair.h"

namespace fleetmem::core {
namespace {

constexpr int kDimension = 256 + 3;

class CentroidSource {
 public:
  explicit CentroidSource(uint64_t seed) : rng_(seed) {
    for (int b = 0; b < 50; ++b) centres_.push_back(Gaussian(1.0f));
  }
  Eigen::VectorXf Next() {
    const Eigen::VectorXf& centre = centres_[rng_() % centres_.size()];
    return centre + Gaussian(0.05f);
  }

 private:
  Eigen::VectorXf Gaussian(float sigma) {
    std::normal_distribution<float> normal(0.0f, sigma);
    Eigen::VectorXf v(kDimension);
    for (int i = 0; i < kDimension; ++i) v[i] = normal(rng_);
    return v;
  }
  std::mt19937_64 rng_;
  std::vector<Eigen::VectorXf> centres_;
};

// The paper's Algorithm 2: distances kept in a matrix (computed once per
// centroid), the minimum searched over all live pairs at every removal.
class DistanceMatrixForgetting {
 public:
  void Insert(const Eigen::VectorXf& point) {
    const size_t slot = points_.size();
    points_.push_back(point);
    live_.push_back(true);
    for (std::vector<double>& row : distance_) row.push_back(0.0);
    distance_.emplace_back(slot + 1, 0.0);
    for (size_t j = 0; j < slot; ++j) {
      if (!live_[j]) continue;
      const double d = (points_[j] - point).norm();
      distance_[slot][j] = d;
      distance_[j][slot] = d;
    }
  }
  // Removes one member of the closest live pair; returns its slot.
  size_t ForgetOne() {
    double best = std::numeric_limits<double>::infinity();
    size_t best_i = 0;
    for (size_t i = 0; i < points_.size(); ++i) {
      if (!live_[i]) continue;
      for (size_t j = i + 1; j < points_.size(); ++j) {
        if (live_[j] && distance_[i][j] < best) {
          best = distance_[i][j];
          best_i = i;
        }
      }
    }
    live_[best_i] = false;
    return best_i;
  }
  // Reuses a dead slot for a new point (keeps the matrix at K x K).
  void Replace(size_t slot, const Eigen::VectorXf& point) {
    points_[slot] = point;
    live_[slot] = true;
    for (size_t j = 0; j < points_.size(); ++j) {
      if (j == slot || !live_[j]) continue;
      const double d = (points_[j] - point).norm();
      distance_[slot][j] = d;
      distance_[j][slot] = d;
    }
  }

 private:
  std::vector<Eigen::VectorXf> points_;
  std::vector<bool> live_;
  std::vector<std::vector<double>> distance_;
};

void BM_ForgetStep_ClosestPairTracker(benchmark::State& state) {
  const int clusters = static_cast<int>(state.range(0));
  CentroidSource source(1);
  ClosestPairTracker tracker;
  uint64_t next_id = 1;
  for (int i = 0; i < clusters; ++i) tracker.Insert(next_id++, source.Next());
  for (auto _ : state) {
    ClosestPairTracker::Pair pair = *tracker.Closest();
    tracker.Remove(pair.a);
    tracker.Insert(next_id++, source.Next());
  }
  state.SetLabel("fleetmem");
}

void BM_ForgetStep_DistanceMatrixScan(benchmark::State& state) {
  const int clusters = static_cast<int>(state.range(0));
  CentroidSource source(1);
  DistanceMatrixForgetting matrix;
  for (int i = 0; i < clusters; ++i) matrix.Insert(source.Next());
  for (auto _ : state) {
    size_t slot = matrix.ForgetOne();
    matrix.Replace(slot, source.Next());
  }
  state.SetLabel("paper's Algorithm 2");
}

BENCHMARK(BM_ForgetStep_ClosestPairTracker)
    ->Arg(100)
    ->Arg(1000)
    ->Arg(5000)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_ForgetStep_DistanceMatrixScan)
    ->Arg(100)
    ->Arg(1000)
    ->Arg(5000)
    ->Unit(benchmark::kMicrosecond);

}  // namespace
}  // namespace fleetmem::core

int main(int argc, char** argv) {
  return fleetmem::bench::Main(
      argc, argv, "fleetmem_forgetting_bench",
      "the forgetting step (Algorithm 2): ClosestPairTracker against the "
      "O(K^2) matrix scan.");
}
