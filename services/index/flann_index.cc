#include "services/index/flann_index.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <exception>
#include <flann/flann.hpp>
#include <new>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/core/feature_space.h"
#include "services/index/index_input.h"

namespace fleetmem::index {
namespace {

using engine::Neighbor;
using engine::SearchParams;
using FlannL2 = flann::Index<flann::L2<float>>;

// Converts the exception in flight (inside a catch block) to a status.
absl::Status ExceptionToStatus(const char* where) {
  try {
    throw;
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError(
        absl::StrCat("flann index: out of memory in ", where));
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("flann index: ", where, ": ", e.what()));
  } catch (...) {
    return absl::InternalError(
        absl::StrCat("flann index: ", where, ": unknown exception"));
  }
}

class FlannIndex final : public engine::PlaceIndex {
 public:
  FlannIndex(size_t dimension, const FlannIndexOptions& options)
      : dimension_(dimension), options_(options) {
    // Unlimited checks search the first tree exactly; FLANN complains on
    // stderr at every search when there are more.
    options_.trees = options_.checks > 0 ? std::max(options_.trees, 1) : 1;
    options_.accept_oversample = std::max(options_.accept_oversample, 1);
  }

  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override;
  absl::Status Remove(std::span<const uint64_t> ids) override;
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override;
  size_t size() const override { return point_of_.size(); }
  size_t dimension() const override { return dimension_; }

 private:
  // One point FLANN knows, by FLANN point id.
  struct Slot {
    uint64_t id = 0;
    const float* row = nullptr;  // into one of blocks_
    bool live = false;
  };

  // Builds fresh trees over the live points, compacted into one block.
  // Changes nothing if FLANN throws.
  absl::Status Rebuild();
  // Forgets every point (no FLANN index while empty).
  void Clear();
  // Up to `knn` (<= size()) approximate nearest live points.
  std::vector<Neighbor> SearchFlann(std::span<const float> query,
                                    size_t knn) const;

  const size_t dimension_;
  FlannIndexOptions options_;
  // Row-major copies of the vectors; FLANN points into them, so a block
  // lives until the next Rebuild or Clear.
  std::vector<std::unique_ptr<float[]>> blocks_;
  // FLANN point id → point. FLANN numbers points 0, 1, 2, ... in the order
  // they were given to it since the index was built; ids survive its
  // internal rebuilds.
  std::vector<Slot> slots_;
  // Our id → FLANN point id, for live points.
  absl::flat_hash_map<uint64_t, size_t> point_of_;
  // Points removed since the trees were built from scratch.
  size_t removed_since_build_ = 0;
  // Null while the index is empty.
  std::unique_ptr<FlannL2> flann_;
};

absl::Status FlannIndex::Add(std::span<const uint64_t> ids,
                             std::span<const std::vector<float>> vectors) {
  if (absl::Status status =
          CheckAddBatch(dimension_, ids, vectors,
                        [this](uint64_t id) { return point_of_.contains(id); });
      !status.ok()) {
    return status;
  }
  if (ids.empty()) return absl::OkStatus();
  const size_t count = ids.size();
  const size_t first_point = slots_.size();
  float* block = nullptr;
  try {
    ReserveGeometric(blocks_, blocks_.size() + 1);
    ReserveGeometric(slots_, slots_.size() + count);
    point_of_.reserve(point_of_.size() + count);
    blocks_.push_back(std::make_unique_for_overwrite<float[]>(
        count * dimension_));  // no throw after this: reserved
    block = blocks_.back().get();
  } catch (...) {
    return ExceptionToStatus("Add");
  }
  for (size_t i = 0; i < count; ++i) {
    std::memcpy(block + i * dimension_, vectors[i].data(),
                dimension_ * sizeof(float));
  }
  flann::Matrix<float> points(block, count, dimension_);
  try {
    if (flann_ == nullptr) {
      auto fresh = std::make_unique<FlannL2>(
          points, flann::KDTreeIndexParams(options_.trees));
      fresh->buildIndex();
      flann_ = std::move(fresh);
    } else {
      flann_->addPoints(points, options_.add_rebuild_factor);
    }
  } catch (...) {
    absl::Status status = ExceptionToStatus("Add");
    // FLANN may hold some of the new points: rebuild from what we had. The
    // new block stays alive until then, so FLANN never points at freed
    // memory.
    if (point_of_.empty()) {
      Clear();
    } else {
      (void)Rebuild();
    }
    return status;
  }
  // Our numbering must be FLANN's; a mismatch would return wrong ids.
  if (flann_->getPoint(first_point) != block ||
      flann_->getPoint(first_point + count - 1) !=
          block + (count - 1) * dimension_) {
    for (size_t i = 0; i < count; ++i) {
      slots_.push_back({ids[i], block + i * dimension_, false});
    }
    (void)Rebuild();
    return absl::InternalError(
        "flann index: FLANN numbered the added points unexpectedly");
  }
  for (size_t i = 0; i < count; ++i) {
    slots_.push_back({ids[i], block + i * dimension_, true});
    point_of_.emplace(ids[i], first_point + i);
  }
  return absl::OkStatus();
}

absl::Status FlannIndex::Remove(std::span<const uint64_t> ids) {
  for (uint64_t id : ids) {
    auto it = point_of_.find(id);
    if (it == point_of_.end()) continue;
    try {
      flann_->removePoint(it->second);
    } catch (...) {
      return ExceptionToStatus("Remove");  // the ids before this one are gone
    }
    slots_[it->second].live = false;
    point_of_.erase(it);
    ++removed_since_build_;
  }
  if (point_of_.empty()) {
    Clear();
  } else if (removed_since_build_ >
             options_.rebuild_removed_fraction * point_of_.size()) {
    // The removal is done either way; a failed rebuild is retried by the
    // next Remove.
    if (absl::Status status = Rebuild(); !status.ok()) {
      FLEETMEM_LOG(kWarning) << status;
    }
  }
  return absl::OkStatus();
}

void FlannIndex::Clear() {
  flann_.reset();
  point_of_.clear();
  slots_.clear();
  blocks_.clear();
  removed_since_build_ = 0;
}

absl::Status FlannIndex::Rebuild() {
  const size_t count = point_of_.size();
  try {
    auto block = std::make_unique_for_overwrite<float[]>(count * dimension_);
    std::vector<Slot> slots;
    slots.reserve(count);
    absl::flat_hash_map<uint64_t, size_t> point_of;
    point_of.reserve(count);
    for (const Slot& slot : slots_) {
      if (!slot.live) continue;
      float* row = block.get() + slots.size() * dimension_;
      std::memcpy(row, slot.row, dimension_ * sizeof(float));
      point_of.emplace(slot.id, slots.size());
      slots.push_back({slot.id, row, true});
    }
    auto fresh = std::make_unique<FlannL2>(
        flann::Matrix<float>(block.get(), count, dimension_),
        flann::KDTreeIndexParams(options_.trees));
    fresh->buildIndex();
    std::vector<std::unique_ptr<float[]>> blocks;
    blocks.push_back(std::move(block));
    // The old trees go before the blocks they point into.
    flann_ = std::move(fresh);
    blocks_ = std::move(blocks);
    slots_ = std::move(slots);
    point_of_ = std::move(point_of);
    removed_since_build_ = 0;
    return absl::OkStatus();
  } catch (...) {
    return ExceptionToStatus("Rebuild");
  }
}

std::vector<Neighbor> FlannIndex::SearchFlann(std::span<const float> query,
                                              size_t knn) const {
  std::vector<size_t> points(knn);
  std::vector<float> squared(knn);
  flann::Matrix<float> queries(const_cast<float*>(query.data()), 1, dimension_);
  flann::Matrix<size_t> point_matrix(points.data(), 1, knn);
  flann::Matrix<float> squared_matrix(squared.data(), 1, knn);
  flann::SearchParams search(
      options_.checks > 0 ? options_.checks : flann::FLANN_CHECKS_UNLIMITED);
  search.cores = 1;
  const int found =
      flann_->knnSearch(queries, point_matrix, squared_matrix, knn, search);
  std::vector<Neighbor> neighbors;
  neighbors.reserve(found);
  for (int i = 0; i < found; ++i) {
    if (points[i] >= slots_.size() || !slots_[points[i]].live) continue;
    neighbors.push_back(
        {slots_[points[i]].id, std::sqrt(std::max(0.0f, squared[i]))});
  }
  return neighbors;
}

absl::StatusOr<std::vector<Neighbor>> FlannIndex::Search(
    std::span<const float> query, const SearchParams& params) const {
  if (absl::Status status = CheckQuery(dimension_, query); !status.ok()) {
    return status;
  }
  // FLANN holds normalised copies: the query is normalised the same way.
  std::vector<float> unit;
  if (params.unit_query) {
    unit = core::NormalizedCode(query);
    query = unit;
  }
  const size_t count = size();
  if (count == 0 || params.k == 0) return std::vector<Neighbor>();
  auto nearest_first = [](const Neighbor& a, const Neighbor& b) {
    return a.distance != b.distance ? a.distance < b.distance : a.id < b.id;
  };
  try {
    std::vector<Neighbor> neighbors;
    if (!params.accept) {
      neighbors = SearchFlann(query, std::min(params.k, count));
    } else {
      const size_t oversample = options_.accept_oversample;
      size_t knn =
          params.k >= count / oversample ? count : params.k * oversample;
      while (true) {
        neighbors = SearchFlann(query, knn);
        std::erase_if(neighbors, [&params](const Neighbor& neighbor) {
          return !params.accept(neighbor.id);
        });
        if (neighbors.size() >= params.k || knn == count) break;
        knn = std::min(count, 2 * knn);
      }
    }
    std::sort(neighbors.begin(), neighbors.end(), nearest_first);
    if (neighbors.size() > params.k) neighbors.resize(params.k);
    return neighbors;
  } catch (...) {
    return ExceptionToStatus("Search");
  }
}

}  // namespace

std::unique_ptr<engine::PlaceIndex> NewFlannIndex(
    size_t dimension, const FlannIndexOptions& options) {
  return std::make_unique<FlannIndex>(dimension, options);
}

}  // namespace fleetmem::index
