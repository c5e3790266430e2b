#include "services/core/closest_pair.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <new>

#include "absl/strings/str_cat.h"
#include "services/core/hnsw_graph.h"

namespace fleetmem::core {
namespace {

constexpr double kInfinity = std::numeric_limits<double>::infinity();

// Euclidean distance, computed in float (vectorised; this is the hot loop of
// forgetting) and symmetric bit for bit — (a - b) and (b - a) differ only in
// sign, and Eigen reduces both in the same order — so ties are seen the same
// way from both ends. Points of different dimension are infinitely far apart.
double Distance(Eigen::Map<const Eigen::VectorXf> a,
                Eigen::Map<const Eigen::VectorXf> b) {
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
  if (other.graph_ == nullptr) return;
  for (auto& [id, entry] : points_) entry.point = other.PointOf(entry);
  BuildGraph();
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

ClosestPairTracker::PointView ClosestPairTracker::PointOf(
    const Entry& entry) const {
  if (graph_ == nullptr)
    return PointView(entry.point.data(), entry.point.size());
  return PointView(graph_->hnsw.Vector(entry.slot),
                   static_cast<Eigen::Index>(graph_->hnsw.dimension()));
}

std::vector<uint64_t> ClosestPairTracker::Candidates(PointView point,
                                                     size_t count) const {
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
  Entry& entry = points_[id];
  entry.point = point;
  const PointView view(entry.point.data(), entry.point.size());
  uint64_t best = 0;
  double best_distance = kInfinity;
  bool found = false;
  for (uint64_t other_id : Candidates(view, options_.reverse_candidates)) {
    if (other_id == id) continue;
    Entry& other = points_.at(other_id);
    const double d = Distance(view, PointOf(other));
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
    DropGraph();
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
  const PointView point = PointOf(entry);
  for (uint64_t other_id : Candidates(
           point, std::max<size_t>(options_.reverse_candidates / 4, 2))) {
    if (other_id == id) continue;
    const double d = Distance(point, PointOf(points_.at(other_id)));
    if (!found || Better(d, other_id, best_distance, best)) {
      best = other_id;
      best_distance = d;
      found = true;
    }
  }
  if (found) SetNeighbour(id, entry, best, best_distance);
}

void ClosestPairTracker::BuildGraph() {
  if (graph_ != nullptr) DropGraph();
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

void ClosestPairTracker::DropGraph() {
  for (auto& [id, entry] : points_) entry.point = PointOf(entry);
  graph_.reset();
}

void ClosestPairTracker::AddToGraph(uint64_t id, Entry& entry) {
  entry.slot = graph_->hnsw.Add(entry.point.data());
  if (entry.slot >= graph_->slot_id.size()) {
    graph_->slot_id.resize(entry.slot + 1);
  }
  graph_->slot_id[entry.slot] = id;
  entry.point = Eigen::VectorXf();  // the graph holds it now
}

std::span<const float> ClosestPairTracker::point(uint64_t id) const {
  auto it = points_.find(id);
  if (it == points_.end()) return {};
  const PointView view = PointOf(it->second);
  return {view.data(), static_cast<size_t>(view.size())};
}

std::vector<uint64_t> ClosestPairTracker::ids() const {
  std::vector<uint64_t> out;
  out.reserve(points_.size());
  for (const auto& [id, entry] : points_) out.push_back(id);
  std::sort(out.begin(), out.end());
  return out;
}

// Version and kind of the layout Save writes.
constexpr uint32_t kTrackerFormat = 0x43505431;  // "CPT1"

void ClosestPairTracker::Save(ByteWriter& out) const {
  out.Put<uint32_t>(kTrackerFormat);
  const uint64_t dimension =
      points_.empty() ? 0 : PointOf(points_.begin()->second).size();
  out.Put<uint64_t>(dimension);
  out.Put<uint64_t>(points_.size());
  for (const auto& [id, entry] : points_) {
    out.Put<uint64_t>(id);
    out.Put<uint8_t>(entry.has_neighbour ? 1 : 0);
    out.Put<uint64_t>(entry.neighbour);
    out.Put<double>(entry.distance);
    out.Put<uint32_t>(entry.slot);
    out.PutBytes(PointOf(entry).data(), dimension * sizeof(float));
    out.Put<uint64_t>(entry.keepers.size());
    out.PutBytes(entry.keepers.data(), entry.keepers.size() * sizeof(uint64_t));
  }
  out.Put<uint8_t>(graph_ != nullptr ? 1 : 0);
  if (graph_ == nullptr) return;
  graph_->hnsw.Save(out);
  out.Put<uint64_t>(graph_->slot_id.size());
  out.PutBytes(graph_->slot_id.data(),
               graph_->slot_id.size() * sizeof(uint64_t));
}

absl::Status ClosestPairTracker::Load(ByteReader& in) {
  if (!points_.empty()) {
    return absl::FailedPreconditionError(
        "closest-pair tracker: Load into a used tracker");
  }
  absl::Status status;
  try {
    status = LoadOrThrow(in);
  } catch (const std::bad_alloc&) {
    status = absl::ResourceExhaustedError(
        "out of memory while loading the closest-pair tracker");
  }
  if (!status.ok()) {
    points_.clear();
    by_distance_.clear();
    graph_.reset();
  }
  return status;
}

absl::Status ClosestPairTracker::LoadOrThrow(ByteReader& in) {
  auto malformed = [](auto... what) {
    return absl::DataLossError(
        absl::StrCat("closest-pair tracker snapshot: ", what...));
  };
  uint32_t format = 0;
  uint64_t dimension = 0, count = 0;
  if (!in.Get(&format) || format != kTrackerFormat || !in.Get(&dimension) ||
      !in.Get(&count) ||
      count > in.remaining() / (41 + dimension * sizeof(float))) {
    return malformed("bad header");
  }
  points_.reserve(count);
  size_t keeper_links = 0;
  for (uint64_t i = 0; i < count; ++i) {
    uint64_t id = 0, keepers = 0;
    uint8_t has_neighbour = 0;
    Entry entry;
    entry.point.resize(static_cast<Eigen::Index>(dimension));
    if (!in.Get(&id) || !in.Get(&has_neighbour) || !in.Get(&entry.neighbour) ||
        !in.Get(&entry.distance) || !in.Get(&entry.slot) ||
        !in.GetBytes(entry.point.data(), dimension * sizeof(float)) ||
        !in.Get(&keepers) || keepers > in.remaining() / sizeof(uint64_t)) {
      return malformed("truncated point ", i);
    }
    entry.keepers.resize(keepers);
    in.GetBytes(entry.keepers.data(), keepers * sizeof(uint64_t));
    entry.has_neighbour = has_neighbour != 0;
    keeper_links += keepers;
    if (!points_.emplace(id, std::move(entry)).second) {
      return malformed("point ", id, " twice");
    }
  }
  // Each neighbour link has its keeper entry at the other end, and no
  // keeper entry is without its link.
  size_t neighbour_links = 0;
  for (const auto& [id, entry] : points_) {
    for (uint64_t keeper : entry.keepers) {
      auto it = points_.find(keeper);
      if (it == points_.end() || !it->second.has_neighbour ||
          it->second.neighbour != id) {
        return malformed("point ", id, " has a stray keeper");
      }
    }
    if (!entry.has_neighbour) continue;
    if (entry.neighbour == id || !points_.contains(entry.neighbour) ||
        !(entry.distance >= 0.0) || !std::isfinite(entry.distance)) {
      return malformed("point ", id, " has a bad neighbour");
    }
    ++neighbour_links;
    by_distance_.insert({entry.distance, id});
  }
  if (neighbour_links != keeper_links) return malformed("unpaired keepers");
  uint8_t has_graph = 0;
  if (!in.Get(&has_graph)) return malformed("truncated");
  if (has_graph == 0) return absl::OkStatus();
  if (count == 0) return malformed("a graph without points");
  graph_ = std::make_unique<Graph>(dimension, options_);
  absl::StatusOr<std::unique_ptr<HnswGraph>> graph =
      HnswGraph::Load(dimension, options_.graph, in);
  if (!graph.ok()) return graph.status();
  uint64_t slots = 0;
  if (!in.Get(&slots) || slots != (*graph)->slot_count() ||
      (*graph)->size() != count) {
    return malformed("the graph does not hold the points");
  }
  graph_->slot_id.resize(slots);
  in.GetBytes(graph_->slot_id.data(), slots * sizeof(uint64_t));
  for (const auto& [id, entry] : points_) {
    if (!(*graph)->contains(entry.slot) || graph_->slot_id[entry.slot] != id ||
        !std::equal(entry.point.begin(), entry.point.end(),
                    (*graph)->Vector(entry.slot))) {
      return malformed("point ", id, " is not in its graph slot");
    }
  }
  graph_->hnsw = std::move(**graph);
  // The graph holds each point: one copy.
  for (auto& [id, entry] : points_) entry.point = Eigen::VectorXf();
  return absl::OkStatus();
}

}  // namespace fleetmem::core
