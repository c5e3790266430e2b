#include "clients/robot/sensing/code_search.h"

#include <algorithm>
#include <cmath>
#include <numeric>
#include <utility>

namespace fleetmem::robot {

float CosineSimilarity(std::span<const float> a, std::span<const float> b) {
  const std::vector<float> unit_a = core::NormalizedCode(a);
  const std::vector<float> unit_b = core::NormalizedCode(b);
  auto zero = [](const std::vector<float>& v) {
    return std::all_of(v.begin(), v.end(), [](float x) { return x == 0.0f; });
  };
  if (zero(unit_a) || zero(unit_b)) {
    return zero(unit_a) == zero(unit_b) ? 1.0f : 0.0f;
  }
  double dot = 0.0;
  const size_t n = std::min(unit_a.size(), unit_b.size());
  for (size_t i = 0; i < n; ++i)
    dot += static_cast<double>(unit_a[i]) * unit_b[i];
  return static_cast<float>(std::clamp(dot, -1.0, 1.0));
}

void BruteForceIndex::Add(std::span<const float> code, double label) {
  std::vector<float> unit = core::NormalizedCode(code);
  unit.resize(dimension_, 0.0f);
  normalised_.insert(normalised_.end(), unit.begin(), unit.end());
  labels_.push_back(label);
}

std::vector<double> BruteForceIndex::Search(std::span<const float> query,
                                            size_t k) const {
  std::vector<double> labels;
  for (const Neighbour& n : SearchScored(query, k)) labels.push_back(n.label);
  return labels;
}

std::vector<BruteForceIndex::Neighbour> BruteForceIndex::SearchScored(
    std::span<const float> query, size_t k) const {
  std::vector<float> q = core::NormalizedCode(query);
  q.resize(dimension_, 0.0f);
  std::vector<std::pair<float, size_t>> scored(labels_.size());
  for (size_t row = 0; row < labels_.size(); ++row) {
    const float* r = normalised_.data() + row * dimension_;
    float sum = 0.0f;
    for (size_t i = 0; i < dimension_; ++i) {
      const float d = r[i] - q[i];
      sum += d * d;
    }
    scored[row] = {sum, row};
  }
  k = std::min(k, scored.size());
  std::partial_sort(scored.begin(), scored.begin() + k, scored.end());
  std::vector<Neighbour> found;
  found.reserve(k);
  for (size_t i = 0; i < k; ++i) {
    found.push_back({.label = labels_[scored[i].second],
                     .distance = std::sqrt(scored[i].first)});
  }
  return found;
}

double PlaceDistance(const core::Place& a, const core::Place& b) {
  return std::sqrt((a.x - b.x) * (a.x - b.x) + (a.y - b.y) * (a.y - b.y) +
                   (a.z - b.z) * (a.z - b.z));
}

int FirstCorrectRank(std::span<const core::Place> retrieved,
                     const core::Place& query, double tolerance) {
  for (size_t i = 0; i < retrieved.size(); ++i) {
    if (PlaceDistance(retrieved[i], query) <= tolerance) {
      return static_cast<int>(i) + 1;
    }
  }
  return 0;
}

}  // namespace fleetmem::robot
