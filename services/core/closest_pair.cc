#include "services/core/closest_pair.h"

#include <algorithm>
#include <limits>

#include "services/core/hnsw_graph.h"

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

// The HNSW graph over the points and the point id of each of its slots.
struct ClosestPairTracker::Graph {
  Graph(size_t dimension, const ClosestPairOptions& options)
      : hnsw(dimension, options.graph) {}
  HnswGraph hnsw;
  std::vector<uint64_t> slot_id;  // slot -> point id
};

ClosestPairTracker::ClosestPairTracker(ClosestPairOptions options)
    : options_(options) {
  options_.exact_below = std::max<size_t>(options_.exact_below, 2);
}
ClosestPairTracker::~ClosestPairTracker() = default;
ClosestPairTracker::ClosestPairTracker(ClosestPairTracker&&) noexcept = default;
ClosestPairTracker& ClosestPairTracker::operator=(
    ClosestPairTracker&&) noexcept = default;

ClosestPairTracker::ClosestPairTracker(const ClosestPairTracker& other)
    : options_(other.options_),
      points_(other.points_),
      by_distance_(other.by_distance_) {
  if (other.graph_ != nullptr) BuildGraph();
}

ClosestPairTracker& ClosestPairTracker::operator=(
    const ClosestPairTracker& other) {
  if (this != &other) *this = ClosestPairTracker(other);
  return *this;
}

void ClosestPairTracker::SetNeighbour(uint64_t id, Entry& entry,
                                      uint64_t neighbour, double distance) {
  ClearNeighbour(id, entry);
  entry.neighbour = neighbour;
  entry.distance = distance;
  entry.has_neighbour = true;
  points_.at(neighbour).keepers.push_back(id);
  by_distance_.insert({distance, id});
}

void ClosestPairTracker::ClearNeighbour(uint64_t id, Entry& entry) {
  if (!entry.has_neighbour) return;
  by_distance_.erase({entry.distance, id});
  auto held = points_.find(entry.neighbour);
  if (held != points_.end()) std::erase(held->second.keepers, id);
  entry.has_neighbour = false;
  entry.neighbour = 0;
  entry.distance = kInfinity;
}

std::vector<uint64_t> ClosestPairTracker::Candidates(
    const Eigen::VectorXf& point, size_t count) const {
  std::vector<uint64_t> ids;
  if (graph_ == nullptr) {
    ids.reserve(points_.size());
    for (const auto& [id, entry] : points_) ids.push_back(id);
    return ids;
  }
  for (const auto& [squared, slot] : graph_->hnsw.Search(point.data(), count)) {
    ids.push_back(graph_->slot_id[slot]);
  }
  return ids;
}

void ClosestPairTracker::Insert(uint64_t id, const Eigen::VectorXf& point) {
  Remove(id);  // contract says absent; stay consistent if not
  Entry& entry = points_.emplace(id, Entry{point}).first->second;
  uint64_t best = 0;
  double best_distance = kInfinity;
  bool found = false;
  for (uint64_t other_id : Candidates(point, options_.reverse_candidates)) {
    if (other_id == id) continue;
    Entry& other = points_.at(other_id);
    const double d = Distance(point, other.point);
    if (!found || Better(d, other_id, best_distance, best)) {
      best = other_id;
      best_distance = d;
      found = true;
    }
    if (!other.has_neighbour ||
        Better(d, id, other.distance, other.neighbour)) {
      SetNeighbour(other_id, other, id, d);
    }
  }
  if (found) SetNeighbour(id, entry, best, best_distance);
  if (graph_ != nullptr) {
    AddToGraph(id, entry);
  } else if (points_.size() >= options_.exact_below) {
    BuildGraph();
  }
}

void ClosestPairTracker::Remove(uint64_t id) {
  auto it = points_.find(id);
  if (it == points_.end()) return;
  Entry& entry = it->second;
  ClearNeighbour(id, entry);
  const std::vector<uint64_t> keepers = std::move(entry.keepers);
  if (graph_ != nullptr) {
    graph_->hnsw.Remove(entry.slot);
  }
  points_.erase(it);
  if (graph_ != nullptr && points_.size() < options_.exact_below / 2) {
    graph_.reset();
  }
  for (uint64_t keeper : keepers) {
    Entry& other = points_.at(keeper);
    // Its neighbour is gone: the entry no longer holds it.
    by_distance_.erase({other.distance, keeper});
    other.has_neighbour = false;
    Recompute(keeper, other);
  }
}

std::optional<ClosestPairTracker::Pair> ClosestPairTracker::Closest() const {
  if (by_distance_.empty()) return std::nullopt;
  const auto& [distance, id] = *by_distance_.begin();
  const uint64_t neighbour = points_.at(id).neighbour;
  return Pair{std::min(id, neighbour), std::max(id, neighbour), distance};
}

void ClosestPairTracker::Recompute(uint64_t id, Entry& entry) {
  ClearNeighbour(id, entry);
  uint64_t best = 0;
  double best_distance = kInfinity;
  bool found = false;
  // Two candidates at least: the point itself is among them.
  for (uint64_t other_id : Candidates(
           entry.point, std::max<size_t>(options_.reverse_candidates / 4, 2))) {
    if (other_id == id) continue;
    const double d = Distance(entry.point, points_.at(other_id).point);
    if (!found || Better(d, other_id, best_distance, best)) {
      best = other_id;
      best_distance = d;
      found = true;
    }
  }
  if (found) SetNeighbour(id, entry, best, best_distance);
}

void ClosestPairTracker::BuildGraph() {
  graph_.reset();
  if (points_.empty()) return;
  const size_t dimension =
      static_cast<size_t>(points_.begin()->second.point.size());
  graph_ = std::make_unique<Graph>(dimension, options_);
  graph_->hnsw.Reserve(2 * points_.size());
  // In id order, so that the graph (and every later answer) depends only on
  // the points, not on the hash map's iteration order.
  std::vector<uint64_t> ids;
  ids.reserve(points_.size());
  for (const auto& [id, entry] : points_) ids.push_back(id);
  std::sort(ids.begin(), ids.end());
  for (uint64_t id : ids) AddToGraph(id, points_.at(id));
}

void ClosestPairTracker::AddToGraph(uint64_t id, Entry& entry) {
  entry.slot = graph_->hnsw.Add(entry.point.data());
  if (entry.slot >= graph_->slot_id.size()) {
    graph_->slot_id.resize(entry.slot + 1);
  }
  graph_->slot_id[entry.slot] = id;
}

}  // namespace fleetmem::core
