#include "services/index/hnsw_index.h"

#include <algorithm>
#include <cmath>
#include <new>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/str_cat.h"
#include "services/core/hnsw_graph.h"
#include "services/index/exact_index.h"
#include "services/index/index_input.h"

namespace fleetmem::index {
namespace {

using engine::Neighbor;
using engine::SearchParams;

// Sorts by (distance, id) and keeps the first k.
void KeepNearest(std::vector<Neighbor>& neighbors, size_t k) {
  auto closer = [](const Neighbor& a, const Neighbor& b) {
    return a.distance < b.distance || (a.distance == b.distance && a.id < b.id);
  };
  if (neighbors.size() > k) {
    std::partial_sort(neighbors.begin(), neighbors.begin() + k, neighbors.end(),
                      closer);
    neighbors.resize(k);
  } else {
    std::sort(neighbors.begin(), neighbors.end(), closer);
  }
}

class HnswIndex final : public engine::PlaceIndex {
 public:
  HnswIndex(size_t dimension, HnswIndexOptions options)
      : options_(options),
        graph_(dimension,
               core::HnswGraphOptions{
                   .m = options.m,
                   .ef_construction = options.ef_construction,
                   .ef_search = options.ef_search,
                   .seed = options.seed,
                   .repair_probability = options.repair_probability}) {}

  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override;
  absl::Status Remove(std::span<const uint64_t> ids) override;
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override;
  size_t size() const override { return slot_of_.size(); }
  size_t dimension() const override { return graph_.dimension(); }

  void set_ef_search(size_t ef) { graph_.set_ef_search(ef); }

  // Calls visit(id, vector) for every stored vector.
  void ForEach(const std::function<void(uint64_t, std::span<const float>)>&
                   visit) const {
    for (const auto& [id, slot] : slot_of_) {
      visit(id, std::span<const float>(graph_.Vector(slot), dimension()));
    }
  }

 private:
  // Every accepted vector's distance to `query`, by scanning.
  std::vector<Neighbor> Scan(std::span<const float> query,
                             const SearchParams& params) const;

  const HnswIndexOptions options_;
  core::HnswGraph graph_;
  absl::flat_hash_map<uint64_t, uint32_t> slot_of_;  // id -> slot
  std::vector<uint64_t> id_of_;                      // slot -> id
};

absl::Status HnswIndex::Add(std::span<const uint64_t> ids,
                            std::span<const std::vector<float>> vectors) {
  if (absl::Status status =
          CheckAddBatch(dimension(), ids, vectors,
                        [this](uint64_t id) { return slot_of_.contains(id); });
      !status.ok()) {
    return status;
  }
  try {
    graph_.Reserve(slot_of_.size() + ids.size());
    slot_of_.reserve(slot_of_.size() + ids.size());
    id_of_.reserve(slot_of_.size() + ids.size());
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("HNSW index: out of memory in Add");
  }
  for (size_t i = 0; i < ids.size(); ++i) {
    const uint32_t slot = graph_.Add(vectors[i].data());
    if (slot >= id_of_.size()) id_of_.resize(slot + 1);
    id_of_[slot] = ids[i];
    slot_of_.emplace(ids[i], slot);
  }
  return absl::OkStatus();
}

absl::Status HnswIndex::Remove(std::span<const uint64_t> ids) {
  for (uint64_t id : ids) {
    auto it = slot_of_.find(id);
    if (it == slot_of_.end()) continue;
    graph_.Remove(it->second);
    slot_of_.erase(it);
  }
  return absl::OkStatus();
}

std::vector<Neighbor> HnswIndex::Scan(std::span<const float> query,
                                      const SearchParams& params) const {
  std::vector<Neighbor> all;
  all.reserve(slot_of_.size());
  for (const auto& [id, slot] : slot_of_) {
    if (params.accept && !params.accept(id)) continue;
    const float squared = graph_.SquaredDistance(query.data(), slot);
    all.push_back({id, std::sqrt(std::max(0.0f, squared))});
  }
  return all;
}

absl::StatusOr<std::vector<Neighbor>> HnswIndex::Search(
    std::span<const float> query, const SearchParams& params) const {
  if (absl::Status status = CheckQuery(dimension(), query); !status.ok()) {
    return status;
  }
  const size_t live = slot_of_.size();
  if (live == 0 || params.k == 0) return std::vector<Neighbor>();
  try {
    size_t asked =
        params.accept ? params.k * options_.accept_oversample : params.k;
    while (true) {
      if (params.accept && asked >= live / 2) {
        std::vector<Neighbor> all = Scan(query, params);
        KeepNearest(all, params.k);
        return all;
      }
      std::vector<Neighbor> neighbors;
      for (const auto& [squared, slot] :
           graph_.Search(query.data(), std::min(asked, live))) {
        const uint64_t id = id_of_[slot];
        if (params.accept && !params.accept(id)) continue;
        neighbors.push_back({id, std::sqrt(std::max(0.0f, squared))});
      }
      if (neighbors.size() >= params.k || asked >= live || !params.accept) {
        KeepNearest(neighbors, params.k);
        return neighbors;
      }
      asked *= 4;
    }
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("HNSW index: out of memory in Search");
  }
}

// Exact below options.hnsw_from vectors, HNSW from it on (and exact again
// below half of it). The switch moves every vector into the other index
// (one-off: up to ~20 s at 20,000 x 256-d on the 2-core reference machine,
// under the fleet's writer lock; docs/performance.md).
class TieredIndex final : public engine::PlaceIndex {
 public:
  TieredIndex(size_t dimension, TieredIndexOptions options)
      : dimension_(dimension),
        options_(options),
        active_(NewExactIndex(dimension)) {}

  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override {
    absl::Status status = active_->Add(ids, vectors);
    if (status.ok() && !graph_ && active_->size() >= options_.hnsw_from) {
      status = Switch(/*to_graph=*/true);
    }
    return status;
  }
  absl::Status Remove(std::span<const uint64_t> ids) override {
    absl::Status status = active_->Remove(ids);
    if (status.ok() && graph_ && active_->size() < options_.hnsw_from / 2) {
      status = Switch(/*to_graph=*/false);
    }
    return status;
  }
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override {
    return active_->Search(query, params);
  }
  size_t size() const override { return active_->size(); }
  engine::PlaceIndex& active() { return *active_; }
  size_t dimension() const override { return dimension_; }

 private:
  // Moves every vector into a new index of the other kind; on failure the
  // current one stays.
  absl::Status Switch(bool to_graph) {
    std::unique_ptr<engine::PlaceIndex> next =
        to_graph ? NewHnswIndex(dimension_, options_.hnsw)
                 : NewExactIndex(dimension_);
    std::vector<uint64_t> ids;
    std::vector<std::vector<float>> vectors;
    auto collect = [&](uint64_t id, std::span<const float> vector) {
      ids.push_back(id);
      vectors.emplace_back(vector.begin(), vector.end());
    };
    if (graph_) {
      static_cast<const HnswIndex&>(*active_).ForEach(collect);
    } else {
      ForEachExactVector(*active_, collect);
    }
    // In id order: the graph depends on the vectors, not on storage order.
    std::vector<size_t> order(ids.size());
    for (size_t i = 0; i < order.size(); ++i) order[i] = i;
    std::sort(order.begin(), order.end(),
              [&](size_t a, size_t b) { return ids[a] < ids[b]; });
    std::vector<uint64_t> sorted_ids;
    std::vector<std::vector<float>> sorted_vectors;
    sorted_ids.reserve(ids.size());
    sorted_vectors.reserve(ids.size());
    for (size_t i : order) {
      sorted_ids.push_back(ids[i]);
      sorted_vectors.push_back(std::move(vectors[i]));
    }
    absl::Status status = next->Add(sorted_ids, sorted_vectors);
    if (!status.ok()) return status;
    active_ = std::move(next);
    graph_ = to_graph;
    return absl::OkStatus();
  }

  const size_t dimension_;
  const TieredIndexOptions options_;
  std::unique_ptr<engine::PlaceIndex> active_;
  bool graph_ = false;
};

}  // namespace

std::unique_ptr<engine::PlaceIndex> NewHnswIndex(size_t dimension,
                                                 HnswIndexOptions options) {
  return std::make_unique<HnswIndex>(dimension, options);
}

bool SetHnswEfSearch(engine::PlaceIndex& index, size_t ef_search) {
  if (auto* tiered = dynamic_cast<TieredIndex*>(&index)) {
    return SetHnswEfSearch(tiered->active(), ef_search);
  }
  auto* hnsw = dynamic_cast<HnswIndex*>(&index);
  if (hnsw == nullptr) return false;
  hnsw->set_ef_search(ef_search);
  return true;
}

std::unique_ptr<engine::PlaceIndex> NewTieredIndex(size_t dimension,
                                                   TieredIndexOptions options) {
  return std::make_unique<TieredIndex>(dimension, options);
}

}  // namespace fleetmem::index
