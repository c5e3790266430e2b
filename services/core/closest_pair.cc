#include "services/core/closest_pair.h"

#include <limits>

namespace fleetmem::core {
namespace {

constexpr double kInfinity = std::numeric_limits<double>::infinity();

// Euclidean distance, computed in float (vectorised; this is the hot loop of
// forgetting) and symmetric bit for bit — (a - b) and (b - a) differ only in
// sign, and Eigen reduces both in the same order — so ties are seen the same
// way from both ends. Points of different dimension are infinitely far apart.
double Distance(const Eigen::VectorXf& a, const Eigen::VectorXf& b) {
  if (a.size() != b.size()) return kInfinity;
  return static_cast<double>((a - b).norm());
}

// True if `candidate` at `distance` is a better neighbour than the current
// one (nearer; equal distance: smaller id).
bool Better(double distance, uint64_t candidate, double current_distance,
            uint64_t current) {
  return distance < current_distance ||
         (distance == current_distance && candidate < current);
}

}  // namespace

void ClosestPairTracker::Insert(uint64_t id, const Eigen::VectorXf& point) {
  Remove(id);  // contract says absent; stay consistent if not
  Entry entry{point, 0, kInfinity};
  bool has_neighbour = false;
  for (auto& [other_id, other] : points_) {
    const double d = Distance(point, other.point);
    if (!has_neighbour ||
        Better(d, other_id, entry.distance, entry.neighbour)) {
      entry.neighbour = other_id;
      entry.distance = d;
      has_neighbour = true;
    }
    const bool other_has_neighbour = points_.size() > 1;
    if (!other_has_neighbour ||
        Better(d, id, other.distance, other.neighbour)) {
      if (other_has_neighbour) by_distance_.erase({other.distance, other_id});
      other.neighbour = id;
      other.distance = d;
      by_distance_.insert({other.distance, other_id});
    }
  }
  if (has_neighbour) by_distance_.insert({entry.distance, id});
  points_.emplace(id, std::move(entry));
}

void ClosestPairTracker::Remove(uint64_t id) {
  auto it = points_.find(id);
  if (it == points_.end()) return;
  by_distance_.erase({it->second.distance, id});
  points_.erase(it);
  for (auto& [other_id, other] : points_) {
    if (other.neighbour == id) Recompute(other_id, other);
  }
}

std::optional<ClosestPairTracker::Pair> ClosestPairTracker::Closest() const {
  if (by_distance_.empty()) return std::nullopt;
  const auto& [distance, id] = *by_distance_.begin();
  const uint64_t neighbour = points_.at(id).neighbour;
  return Pair{std::min(id, neighbour), std::max(id, neighbour), distance};
}

void ClosestPairTracker::Recompute(uint64_t id, Entry& entry) {
  by_distance_.erase({entry.distance, id});
  bool has_neighbour = false;
  entry.neighbour = 0;
  entry.distance = kInfinity;
  for (const auto& [other_id, other] : points_) {
    if (other_id == id) continue;
    const double d = Distance(entry.point, other.point);
    if (!has_neighbour ||
        Better(d, other_id, entry.distance, entry.neighbour)) {
      entry.neighbour = other_id;
      entry.distance = d;
      has_neighbour = true;
    }
  }
  if (has_neighbour) by_distance_.insert({entry.distance, id});
}

}  // namespace fleetmem::core
