#include "services/core/hnsw_graph.h"

#include <algorithm>

#include "hnswlib/hnswlib.h"

namespace fleetmem::core {

struct HnswGraph::Impl {
  Impl(size_t dimension, size_t capacity, const HnswGraphOptions& options)
      : space(dimension),
        hnsw(&space, capacity, options.m, options.ef_construction,
             options.seed) {
    hnsw.setEf(options.ef_search);
  }
  hnswlib::L2Space space;
  hnswlib::HierarchicalNSW<float> hnsw;
};

HnswGraph::HnswGraph(size_t dimension, HnswGraphOptions options)
    : dimension_(dimension),
      options_(options),
      impl_(std::make_unique<Impl>(dimension, 1024, options)) {}

HnswGraph::~HnswGraph() = default;

void HnswGraph::Reserve(size_t count) {
  if (count > impl_->hnsw.max_elements_) {
    impl_->hnsw.resizeIndex(std::max(count, 2 * impl_->hnsw.max_elements_));
  }
}

uint32_t HnswGraph::Add(const float* vector) {
  if (!free_slots_.empty()) {
    const uint32_t slot = free_slots_.back();
    const hnswlib::tableint internal = impl_->hnsw.label_lookup_.at(slot);
    impl_->hnsw.unmarkDeletedInternal(internal);
    impl_->hnsw.updatePoint(vector, internal, options_.repair_probability);
    free_slots_.pop_back();
    ++live_;
    return slot;
  }
  Reserve(static_cast<size_t>(next_slot_) + 1);
  const uint32_t slot = next_slot_;
  impl_->hnsw.addPoint(vector, slot);
  ++next_slot_;
  ++live_;
  return slot;
}

void HnswGraph::Remove(uint32_t slot) {
  impl_->hnsw.markDelete(slot);
  free_slots_.push_back(slot);
  --live_;
}

std::vector<std::pair<float, uint32_t>> HnswGraph::Search(const float* query,
                                                          size_t k) const {
  std::vector<std::pair<float, uint32_t>> out;
  if (live_ == 0 || k == 0) return out;
  auto found = impl_->hnsw.searchKnn(query, std::min(k, live_));
  out.resize(found.size());
  for (size_t i = found.size(); i-- > 0; found.pop()) {
    out[i] = {found.top().first, static_cast<uint32_t>(found.top().second)};
  }
  return out;
}

void HnswGraph::set_ef_search(size_t ef) { impl_->hnsw.setEf(ef); }

float HnswGraph::SquaredDistance(const float* query, uint32_t slot) const {
  return impl_->hnsw.fstdistfunc_(query, Vector(slot),
                                  impl_->hnsw.dist_func_param_);
}

const float* HnswGraph::Vector(uint32_t slot) const {
  return reinterpret_cast<const float*>(
      impl_->hnsw.getDataByInternalId(impl_->hnsw.label_lookup_.at(slot)));
}

}  // namespace fleetmem::core
