#include "clients/robot/learning/triplets.h"

#include <cmath>
#include <limits>

#include "clients/robot/sensing/code_search.h"

namespace fleetmem::robot::gpl {
namespace {

float SquaredDistance(const std::vector<float>& a,
                      const std::vector<float>& b) {
  float sum = 0.0f;
  for (size_t i = 0; i < a.size() && i < b.size(); ++i) {
    const float d = a[i] - b[i];
    sum += d * d;
  }
  return sum;
}

}  // namespace

std::vector<TripletIndex> MineTriplets(
    std::span<const TripletSample> pool, std::span<const size_t> anchors,
    std::span<const std::vector<float>> descriptors,
    const TripletMiningOptions& options, std::mt19937_64& rng) {
  const bool mine = !descriptors.empty() && descriptors.size() == pool.size();
  std::vector<TripletIndex> out;
  std::vector<size_t> same, other, negatives;
  for (size_t a : anchors) {
    if (a >= pool.size()) continue;
    same.clear();
    other.clear();
    negatives.clear();
    for (size_t j = 0; j < pool.size(); ++j) {
      if (j == a) continue;
      const double d = PlaceDistance(pool[a].place, pool[j].place);
      if (d <= options.positive_radius) {
        (pool[j].domain != pool[a].domain ? other : same).push_back(j);
      } else if (d > options.negative_radius) {
        negatives.push_back(j);
      }
    }
    const std::vector<size_t>& positives =
        options.prefer_other_domain && !other.empty()
            ? other
            : (same.empty() ? other : same);
    if (positives.empty() || negatives.empty()) continue;
    TripletIndex t;
    t.anchor = a;
    t.positive = positives[std::uniform_int_distribution<size_t>(
        0, positives.size() - 1)(rng)];
    std::uniform_int_distribution<size_t> pick(0, negatives.size() - 1);
    t.negative = negatives[pick(rng)];
    if (mine) {
      float nearest = SquaredDistance(descriptors[a], descriptors[t.negative]);
      for (size_t c = 1; c < options.negative_candidates; ++c) {
        const size_t n = negatives[pick(rng)];
        const float d = SquaredDistance(descriptors[a], descriptors[n]);
        if (d < nearest) {
          nearest = d;
          t.negative = n;
        }
      }
    }
    out.push_back(t);
  }
  return out;
}

std::vector<TripletIndex> HardestTriplets(
    std::span<const TripletSample> pool, std::span<const size_t> anchors,
    std::span<const std::vector<float>> descriptors,
    const TripletMiningOptions& options) {
  std::vector<TripletIndex> out;
  if (descriptors.size() != pool.size()) return out;
  for (size_t a : anchors) {
    if (a >= pool.size()) continue;
    TripletIndex t{a, a, a};
    float farthest = -1.0f;
    float nearest = std::numeric_limits<float>::infinity();
    for (size_t j = 0; j < pool.size(); ++j) {
      if (j == a) continue;
      const double d = PlaceDistance(pool[a].place, pool[j].place);
      if (d <= options.positive_radius) {
        const float s = SquaredDistance(descriptors[a], descriptors[j]);
        if (s > farthest) {
          farthest = s;
          t.positive = j;
        }
      } else if (d > options.negative_radius) {
        const float s = SquaredDistance(descriptors[a], descriptors[j]);
        if (s < nearest) {
          nearest = s;
          t.negative = j;
        }
      }
    }
    if (std::isinf(nearest)) continue;
    out.push_back(t);
  }
  return out;
}

}  // namespace fleetmem::robot::gpl
