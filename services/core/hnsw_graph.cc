#include "services/core/hnsw_graph.h"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <limits>
#include <mutex>
#include <new>
#include <optional>
#include <queue>
#include <sstream>
#include <string>
#include <system_error>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "hnswlib/hnswlib.h"
#include "services/core/feature_space.h"

#if defined(__SSE2__)
#include <immintrin.h>
#endif

namespace fleetmem::core {
namespace {

// Squared Euclidean distance between sx * x and sy * y, where x and y are
// `dimension` floats followed by their scales sx, sy and the squared norms
// nx = |sx x|², ny = |sy y|²: nx + ny - 2 sx sy <x, y>, so that the loop
// is a dot product (two operations per coordinate, as hnswlib's inner
// product; its L2 kernel takes three). Rounding leaves an absolute error
// of about 1e-7 (nx + ny): enough to walk the graph; HnswGraph::
// PreciseSquaredDistance scores the answers.
float ScaledSquaredL2(const void* a, const void* b, const void* param) {
  const size_t dimension = *static_cast<const size_t*>(param);
  const float* x = static_cast<const float*>(a);
  const float* y = static_cast<const float*>(b);
  size_t i = 0;
  float dot = 0.0f;
#if defined(__SSE__)
  // Four named accumulators: -O2 does not unroll a loop over an array of
  // them, which then lives on the stack.
  __m128 a0 = _mm_setzero_ps(), a1 = a0, a2 = a0, a3 = a0;
  for (; i + 16 <= dimension; i += 16) {
    a0 = _mm_add_ps(a0, _mm_mul_ps(_mm_loadu_ps(x + i), _mm_loadu_ps(y + i)));
    a1 = _mm_add_ps(
        a1, _mm_mul_ps(_mm_loadu_ps(x + i + 4), _mm_loadu_ps(y + i + 4)));
    a2 = _mm_add_ps(
        a2, _mm_mul_ps(_mm_loadu_ps(x + i + 8), _mm_loadu_ps(y + i + 8)));
    a3 = _mm_add_ps(
        a3, _mm_mul_ps(_mm_loadu_ps(x + i + 12), _mm_loadu_ps(y + i + 12)));
  }
  for (; i + 4 <= dimension; i += 4) {
    a0 = _mm_add_ps(a0, _mm_mul_ps(_mm_loadu_ps(x + i), _mm_loadu_ps(y + i)));
  }
  float lanes[4];
  _mm_storeu_ps(lanes, _mm_add_ps(_mm_add_ps(a0, a1), _mm_add_ps(a2, a3)));
  dot = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
#endif
  for (; i < dimension; ++i) dot += x[i] * y[i];
  const float squared = x[dimension + 1] + y[dimension + 1] -
                        2.0f * (x[dimension] * y[dimension]) * dot;
  return std::max(0.0f, squared);
}

// hnswlib space of `dimension` floats plus a scale and the scaled
// vector's squared norm (HnswGraphOptions::scaled).
class ScaledL2Space final : public hnswlib::SpaceInterface<float> {
 public:
  explicit ScaledL2Space(size_t dimension) : dimension_(dimension) {}
  size_t get_data_size() override { return (dimension_ + 2) * sizeof(float); }
  hnswlib::DISTFUNC<float> get_dist_func() override { return ScaledSquaredL2; }
  void* get_dist_func_param() override { return &dimension_; }

 private:
  size_t dimension_;
};

// An int8 node (HnswGraphOptions::int8): the step s (the value of one
// quantum) and the squared norm of the quantized vector as floats, then
// the dimension's int8 values padded with zeros to a multiple of 16 (the
// kernels' width).
constexpr size_t kInt8Header = 2 * sizeof(float);
size_t Int8Padded(size_t dimension) { return (dimension + 15) / 16 * 16; }
size_t Int8NodeBytes(size_t dimension) {
  return kInt8Header + Int8Padded(dimension);
}

// Writes the int8 node of `scale` times `vector` to `out`: s = max |value|
// / 127, each value rounded to the nearest multiple of s.
void QuantizeScaled(const float* vector, float scale, size_t dimension,
                    char* out) {
  float peak = 0.0f;
  for (size_t i = 0; i < dimension; ++i) {
    peak = std::max(peak, std::fabs(scale * vector[i]));
  }
  const float step = peak / 127.0f;
  auto* values = reinterpret_cast<int8_t*>(out + kInt8Header);
  int64_t sum = 0;
  for (size_t i = 0; i < dimension; ++i) {
    const long q = step > 0.0f ? std::lrint(scale * vector[i] / step) : 0;
    values[i] = static_cast<int8_t>(std::clamp(q, -127L, 127L));
    sum += int64_t{values[i]} * values[i];
  }
  std::fill(values + dimension, values + Int8Padded(dimension), int8_t{0});
  const float norm = step * step * static_cast<float>(sum);
  std::memcpy(out, &step, sizeof(step));
  std::memcpy(out + sizeof(float), &norm, sizeof(norm));
}

// <x, y> of `padded` int8 values (a multiple of 16): products summed in
// int32 (|x y| <= 127², so a sum of 2^17 of them cannot overflow).
int32_t DotInt8(const int8_t* x, const int8_t* y, size_t padded) {
  int32_t dot = 0;
  size_t i = 0;
#if defined(__SSE2__)
  // SSE2 has no sign extension of bytes: interleave each byte with its
  // sign, then multiply pairs of int16 and add them into int32 (madd).
  const __m128i zero = _mm_setzero_si128();
  __m128i sum = zero;
  for (; i < padded; i += 16) {
    const __m128i a = _mm_loadu_si128(reinterpret_cast<const __m128i*>(x + i));
    const __m128i b = _mm_loadu_si128(reinterpret_cast<const __m128i*>(y + i));
    const __m128i sa = _mm_cmpgt_epi8(zero, a), sb = _mm_cmpgt_epi8(zero, b);
    sum = _mm_add_epi32(sum, _mm_madd_epi16(_mm_unpacklo_epi8(a, sa),
                                            _mm_unpacklo_epi8(b, sb)));
    sum = _mm_add_epi32(sum, _mm_madd_epi16(_mm_unpackhi_epi8(a, sa),
                                            _mm_unpackhi_epi8(b, sb)));
  }
  int32_t lanes[4];
  _mm_storeu_si128(reinterpret_cast<__m128i*>(lanes), sum);
  dot = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
#endif
  for (; i < padded; ++i) dot += int32_t{x[i]} * y[i];
  return dot;
}

#if defined(__x86_64__)
// DotInt8 with AVX2 (sign extension to 16 lanes of int16 in one
// instruction, 32 values a step), where the processor has it: the build
// targets baseline x86-64.
__attribute__((target("avx2"))) int32_t DotInt8Avx2(const int8_t* x,
                                                    const int8_t* y,
                                                    size_t padded) {
  __m256i sum = _mm256_setzero_si256();
  size_t i = 0;
  for (; i + 32 <= padded; i += 32) {
    const __m256i a0 = _mm256_cvtepi8_epi16(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(x + i)));
    const __m256i b0 = _mm256_cvtepi8_epi16(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(y + i)));
    const __m256i a1 = _mm256_cvtepi8_epi16(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(x + i + 16)));
    const __m256i b1 = _mm256_cvtepi8_epi16(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(y + i + 16)));
    sum = _mm256_add_epi32(sum, _mm256_madd_epi16(a0, b0));
    sum = _mm256_add_epi32(sum, _mm256_madd_epi16(a1, b1));
  }
  for (; i < padded; i += 16) {
    const __m256i a = _mm256_cvtepi8_epi16(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(x + i)));
    const __m256i b = _mm256_cvtepi8_epi16(
        _mm_loadu_si128(reinterpret_cast<const __m128i*>(y + i)));
    sum = _mm256_add_epi32(sum, _mm256_madd_epi16(a, b));
  }
  const __m128i half = _mm_add_epi32(_mm256_castsi256_si128(sum),
                                     _mm256_extracti128_si256(sum, 1));
  int32_t lanes[4];
  _mm_storeu_si128(reinterpret_cast<__m128i*>(lanes), half);
  return (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
}
#endif

// Squared Euclidean distance between two int8 nodes: nx + ny - 2 sx sy
// <qx, qy>, the distance between the quantized vectors.
template <int32_t (*Dot)(const int8_t*, const int8_t*, size_t)>
float Int8SquaredL2(const void* a, const void* b, const void* param) {
  const size_t padded = *static_cast<const size_t*>(param);
  const char* x = static_cast<const char*>(a);
  const char* y = static_cast<const char*>(b);
  float header_x[2], header_y[2];
  std::memcpy(header_x, x, kInt8Header);
  std::memcpy(header_y, y, kInt8Header);
  const int32_t dot =
      Dot(reinterpret_cast<const int8_t*>(x + kInt8Header),
          reinterpret_cast<const int8_t*>(y + kInt8Header), padded);
  const float squared =
      header_x[1] + header_y[1] -
      2.0f * (header_x[0] * header_y[0]) * static_cast<float>(dot);
  return std::max(0.0f, squared);
}

// hnswlib space of int8 nodes.
class Int8L2Space final : public hnswlib::SpaceInterface<float> {
 public:
  explicit Int8L2Space(size_t dimension) : padded_(Int8Padded(dimension)) {}
  size_t get_data_size() override { return kInt8Header + padded_; }
  hnswlib::DISTFUNC<float> get_dist_func() override {
#if defined(__x86_64__)
    if (__builtin_cpu_supports("avx2")) return Int8SquaredL2<DotInt8Avx2>;
#endif
    return Int8SquaredL2<DotInt8>;
  }
  void* get_dist_func_param() override { return &padded_; }

 private:
  size_t padded_;
};

// options.int8's floats: rows a snapshot reads or writes at a time.
constexpr size_t kFloatChunk = 4096;

std::unique_ptr<hnswlib::SpaceInterface<float>> MakeSpace(
    size_t dimension, const HnswGraphOptions& options) {
  if (options.int8) return std::make_unique<Int8L2Space>(dimension);
  if (options.scaled) return std::make_unique<ScaledL2Space>(dimension);
  return std::make_unique<hnswlib::L2Space>(dimension);
}

// The copy of `node`'s link list on `layer` (0: the base layer), read
// under the node's lock: Link may rewrite it meanwhile.
void CopyLinks(hnswlib::HierarchicalNSW<float>& hnsw, hnswlib::tableint node,
               int layer, std::vector<hnswlib::tableint>& links) {
  std::unique_lock lock(hnsw.link_list_locks_[node]);
  unsigned int* list =
      layer == 0 ? hnsw.get_linklist0(node) : hnsw.get_linklist(node, layer);
  const auto* first = reinterpret_cast<const hnswlib::tableint*>(list + 1);
  links.assign(first, first + hnsw.getListCount(list));
}

// hnswlib's greedy walk from `current` (at squared distance *nearest from
// `data`) down the layers from `top` to bottom + 1: the nearest node it
// reaches. Each list is read under its node's lock.
hnswlib::tableint Descend(hnswlib::HierarchicalNSW<float>& hnsw,
                          const void* data, hnswlib::tableint current,
                          float* nearest, int top, int bottom) {
  std::vector<hnswlib::tableint> links;
  for (int layer = top; layer > bottom; --layer) {
    for (bool moved = true; moved;) {
      moved = false;
      CopyLinks(hnsw, current, layer, links);
      for (hnswlib::tableint candidate : links) {
        const float d = hnsw.fstdistfunc_(
            data, hnsw.getDataByInternalId(candidate), hnsw.dist_func_param_);
        if (d < *nearest) {
          *nearest = d;
          current = candidate;
          moved = true;
        }
      }
    }
  }
  return current;
}

}  // namespace

struct HnswGraph::Impl {
  Impl(size_t dimension, size_t capacity, const HnswGraphOptions& options)
      : space(MakeSpace(dimension, options)),
        hnsw(space.get(), capacity, options.m, options.ef_construction,
             options.seed) {
    hnsw.setEf(options.ef_search);
    if (!options.int8) return;
    rows = options.float_rows
               ? options.float_rows(dimension + 1)
               : std::make_unique<MemoryFloatRows>(dimension + 1);
  }
  std::unique_ptr<hnswlib::SpaceInterface<float>> space;
  hnswlib::HierarchicalNSW<float> hnsw;
  // options.int8: each slot's floats as given and its scale (a row of
  // dimension + 1 floats), read beside Link calls by rescoring searches.
  std::unique_ptr<FloatRows> rows;
  // Where the last Save to a file put the floats (AdoptSavedFloats), and
  // the saved rows written again since (removed slots reused).
  struct SavedFloats {
    FileBytes file;
    uint64_t offset = 0;
    size_t rows = 0;
    std::vector<uint32_t> written_since;
    std::vector<uint32_t> checks;  // each row's RowCheck
  };
  std::optional<SavedFloats> saved;
};

namespace {

// `options` as the graph uses them: int8 nodes hold the scaled vector.
HnswGraphOptions Resolved(HnswGraphOptions options) {
  options.scaled = options.scaled || options.int8;
  return options;
}

}  // namespace

HnswGraph::HnswGraph(size_t dimension, HnswGraphOptions options)
    : dimension_(dimension),
      options_(Resolved(options)),
      impl_(std::make_unique<Impl>(dimension, 1024, options_)) {}

HnswGraph::~HnswGraph() = default;
HnswGraph::HnswGraph(HnswGraph&&) noexcept = default;
HnswGraph& HnswGraph::operator=(HnswGraph&&) noexcept = default;

void HnswGraph::Reserve(size_t count) {
  if (count > impl_->hnsw.max_elements_) {
    impl_->hnsw.resizeIndex(std::max(count, 2 * impl_->hnsw.max_elements_));
  }
}

const void* HnswGraph::Stored(const float* vector, float scale,
                              std::vector<float>& buffer) const {
  if (options_.int8) {
    buffer.resize(Int8NodeBytes(dimension_) / sizeof(float));
    QuantizeScaled(vector, scale, dimension_,
                   reinterpret_cast<char*>(buffer.data()));
    return buffer.data();
  }
  if (!options_.scaled) return vector;
  buffer.resize(dimension_ + 2);
  std::copy(vector, vector + dimension_, buffer.begin());
  buffer[dimension_] = scale;
  buffer[dimension_ + 1] = static_cast<float>(
      ScaledSquaredNorm(std::span<const float>(vector, dimension_), scale));
  return buffer.data();
}

void HnswGraph::ReserveFloats(size_t slots) {
  if (options_.int8) impl_->rows->Reserve(slots);
}

void HnswGraph::KeepFloats(uint32_t slot, const float* vector, float scale) {
  if (!options_.int8) return;
  ReserveFloats(static_cast<size_t>(slot) + 1);
  std::vector<float> row(vector, vector + dimension_);
  row.push_back(scale);
  if (impl_->saved && slot < impl_->saved->rows) {
    impl_->saved->written_since.push_back(slot);  // before: it may fail
  }
  impl_->rows->Write(slot, 1, row.data());
}

const float* HnswGraph::Row(uint32_t slot, std::vector<float>& buffer) const {
  if (slot >= next_slot_) throw std::out_of_range("no such slot");
  if (const float* row = impl_->rows->Find(slot)) return row;
  buffer.resize(dimension_ + 1);
  impl_->rows->Read(slot, 1, buffer.data());
  return buffer.data();
}

uint32_t HnswGraph::Add(const float* raw, float scale) {
  std::vector<float> buffer;
  const void* vector = Stored(raw, scale, buffer);
  if (!free_slots_.empty()) {
    const uint32_t slot = free_slots_.back();
    KeepFloats(slot, raw, scale);
    const hnswlib::tableint internal = impl_->hnsw.label_lookup_.at(slot);
    impl_->hnsw.unmarkDeletedInternal(internal);
    impl_->hnsw.updatePoint(vector, internal, options_.repair_probability);
    free_slots_.pop_back();
    ++live_;
    return slot;
  }
  Reserve(static_cast<size_t>(next_slot_) + 1);
  const uint32_t slot = next_slot_;
  KeepFloats(slot, raw, scale);
  impl_->hnsw.addPoint(vector, slot);
  ++next_slot_;
  ++live_;
  return slot;
}

HnswGraph::Staged HnswGraph::Stage(std::span<const float* const> vectors,
                                   std::span<const float> scales) {
  Staged staged;
  staged.slots.reserve(vectors.size());
  Reserve(static_cast<size_t>(next_slot_) + vectors.size());
  // The floats' blocks too, so that storing the nodes below allocates none.
  ReserveFloats(static_cast<size_t>(next_slot_) + vectors.size());
  auto& hnsw = impl_->hnsw;
  size_t i = 0;
  // Removed slots first, as Add refills them (updatePoint repairs the old
  // node's neighbours: one at a time), then an empty graph's entry point.
  for (; i < vectors.size() &&
         (!free_slots_.empty() || hnsw.cur_element_count == 0);
       ++i) {
    try {
      staged.slots.push_back(Add(vectors[i], scales[i]));
    } catch (const std::system_error&) {  // its floats not written
      staged.linked = staged.slots.size();
      staged.complete = false;
      return staged;
    }
  }
  staged.linked = staged.slots.size();
  const size_t fresh = vectors.size() - i;
  // The new slots' floats, before any node is stored (a write that fails
  // stages none of them), kFloatChunk rows a write.
  if (options_.int8) {
    std::vector<float> rows;
    try {
      for (size_t first = 0; first < fresh; first += kFloatChunk) {
        const size_t count = std::min(kFloatChunk, fresh - first);
        rows.resize(count * (dimension_ + 1));
        for (size_t k = 0; k < count; ++k) {
          const float* vector = vectors[i + first + k];
          float* row = rows.data() + k * (dimension_ + 1);
          std::copy(vector, vector + dimension_, row);
          row[dimension_] = scales[i + first + k];
        }
        impl_->rows->Write(next_slot_ + first, count, rows.data());
      }
    } catch (const std::system_error&) {
      staged.complete = false;
      return staged;
    }
  }
  // The levels, drawn in Add's order, and the upper layers' link lists,
  // allocated before the nodes are stored.
  std::vector<int> levels(fresh);
  std::vector<char*> upper(fresh, nullptr);
  for (size_t k = 0; k < fresh; ++k) {
    levels[k] = hnsw.getRandomLevel(hnsw.mult_);
    if (levels[k] == 0) continue;
    const size_t bytes = hnsw.size_links_per_element_ * levels[k] + 1;
    upper[k] = static_cast<char*>(std::calloc(1, bytes));
    if (upper[k] == nullptr) {
      for (char* list : upper) std::free(list);
      staged.complete = false;
      return staged;
    }
  }
  std::vector<float> buffer;
  for (size_t k = 0; k < fresh; ++k) {
    const uint32_t slot = next_slot_++;
    const hnswlib::tableint internal = hnsw.cur_element_count++;
    hnsw.label_lookup_[slot] = internal;
    hnsw.element_levels_[internal] = levels[k];
    std::memset(hnsw.data_level0_memory_ +
                    internal * hnsw.size_data_per_element_ + hnsw.offsetLevel0_,
                0, hnsw.size_data_per_element_);
    const hnswlib::labeltype label = slot;
    std::memcpy(hnsw.getExternalLabeLp(internal), &label, sizeof(label));
    std::memcpy(hnsw.getDataByInternalId(internal),
                Stored(vectors[i + k], scales[i + k], buffer), hnsw.data_size_);
    hnsw.linkLists_[internal] = upper[k];
    staged.slots.push_back(slot);
    ++live_;
  }
  return staged;
}

// hnswlib's addPoint after its level is drawn and its node stored (0.6's
// insertion: a greedy descent through the layers above the node's, then a
// search and a link on each of its layers), for a node that Stage stored.
// Holds the node's lock throughout, as addPoint does, and reads the entry
// point under hnswlib's `global` lock.
void HnswGraph::Link(const Staged& staged, size_t i) {
  auto& hnsw = impl_->hnsw;
  const hnswlib::tableint node = hnsw.label_lookup_.at(staged.slots[i]);
  const int level = hnsw.element_levels_[node];
  const void* data = hnsw.getDataByInternalId(node);
  const auto distance = [&](hnswlib::tableint other) {
    return hnsw.fstdistfunc_(data, hnsw.getDataByInternalId(other),
                             hnsw.dist_func_param_);
  };
  std::unique_lock node_lock(hnsw.link_list_locks_[node]);
  std::unique_lock top_lock(hnsw.global);
  const int top = hnsw.maxlevel_;
  const hnswlib::tableint entry = hnsw.enterpoint_node_;
  if (level <= top) top_lock.unlock();  // else held until it is the entry
  hnswlib::tableint current = entry;
  if (level < top) {
    float nearest = distance(current);
    current = Descend(hnsw, data, current, &nearest, top, level);
  }
  const bool entry_deleted = hnsw.isMarkedDeleted(entry);
  for (int layer = std::min(level, top); layer >= 0; --layer) {
    auto candidates = hnsw.searchBaseLayer(current, data, layer);
    if (entry_deleted) {
      candidates.emplace(distance(entry), entry);
      if (candidates.size() > hnsw.ef_construction_) candidates.pop();
    }
    current =
        hnsw.mutuallyConnectNewElement(data, node, candidates, layer, false);
  }
  if (level > top) {
    hnsw.enterpoint_node_ = node;
    hnsw.maxlevel_ = level;
  }
}

void HnswGraph::Remove(uint32_t slot) {
  impl_->hnsw.markDelete(slot);
  free_slots_.push_back(slot);
  --live_;
}

std::vector<std::pair<float, uint32_t>> HnswGraph::Search(const float* query,
                                                          size_t k,
                                                          float scale) const {
  std::vector<std::pair<float, uint32_t>> out;
  if (live_ == 0 || k == 0) return out;
  std::vector<float> buffer;
  auto found =
      impl_->hnsw.searchKnn(Stored(query, scale, buffer), std::min(k, live_));
  out.resize(found.size());
  for (size_t i = found.size(); i-- > 0; found.pop()) {
    out[i] = {found.top().first, static_cast<uint32_t>(found.top().second)};
  }
  return out;
}

std::vector<std::pair<float, uint32_t>> HnswGraph::SearchBesideLinks(
    const float* raw, size_t k, float scale) const {
  // hnswlib's searchKnn and searchBaseLayerST (0.6.2), step for step, with
  // each link list copied under its node's lock.
  using Entry = std::pair<float, hnswlib::tableint>;
  using Queue =
      std::priority_queue<Entry, std::vector<Entry>,
                          hnswlib::HierarchicalNSW<float>::CompareByFirst>;
  auto& hnsw = impl_->hnsw;
  std::vector<std::pair<float, uint32_t>> out;
  if (live_ == 0 || k == 0) return out;
  k = std::min(k, live_);
  std::vector<float> buffer;
  const void* query = Stored(raw, scale, buffer);
  const auto distance = [&](hnswlib::tableint node) {
    return hnsw.fstdistfunc_(query, hnsw.getDataByInternalId(node),
                             hnsw.dist_func_param_);
  };
  hnswlib::tableint current;
  int top;
  {
    std::unique_lock lock(hnsw.global);  // a Link raising the top holds it
    current = hnsw.enterpoint_node_;
    top = hnsw.maxlevel_;
  }
  float nearest = distance(current);
  current = Descend(hnsw, query, current, &nearest, top, 0);
  std::vector<hnswlib::tableint> links;
  const size_t ef = std::max(hnsw.ef_, k);
  const bool has_deletions = hnsw.num_deleted_ > 0;
  hnswlib::VisitedList* visited = hnsw.visited_list_pool_->getFreeVisitedList();
  const hnswlib::vl_type tag = visited->curV;
  Queue top_candidates;
  Queue candidates;
  float lower_bound;
  if (!has_deletions || !hnsw.isMarkedDeleted(current)) {
    const float d = distance(current);
    lower_bound = d;
    top_candidates.emplace(d, current);
    candidates.emplace(-d, current);
  } else {
    lower_bound = std::numeric_limits<float>::max();
    candidates.emplace(-lower_bound, current);
  }
  visited->mass[current] = tag;
  while (!candidates.empty()) {
    const Entry closest = candidates.top();
    if (-closest.first > lower_bound &&
        (top_candidates.size() == ef || !has_deletions)) {
      break;
    }
    candidates.pop();
    CopyLinks(hnsw, closest.second, 0, links);
    for (hnswlib::tableint candidate : links) {
      if (visited->mass[candidate] == tag) continue;
      visited->mass[candidate] = tag;
      const float d = distance(candidate);
      if (top_candidates.size() < ef || lower_bound > d) {
        candidates.emplace(-d, candidate);
        if (!has_deletions || !hnsw.isMarkedDeleted(candidate)) {
          top_candidates.emplace(d, candidate);
        }
        if (top_candidates.size() > ef) top_candidates.pop();
        if (!top_candidates.empty()) lower_bound = top_candidates.top().first;
      }
    }
  }
  hnsw.visited_list_pool_->releaseVisitedList(visited);
  while (top_candidates.size() > k) top_candidates.pop();
  out.resize(top_candidates.size());
  for (size_t i = out.size(); i-- > 0; top_candidates.pop()) {
    out[i] = {top_candidates.top().first,
              static_cast<uint32_t>(
                  hnsw.getExternalLabel(top_candidates.top().second))};
  }
  return out;
}

void HnswGraph::set_ef_search(size_t ef) { impl_->hnsw.setEf(ef); }

namespace {

// |scale query - stored_scale stored|² in double precision, term by term.
double PreciseSquared(const float* query, double scale, const float* stored,
                      double stored_scale, size_t dimension) {
  double squared = 0.0;
  for (size_t i = 0; i < dimension; ++i) {
    const double d = scale * query[i] - stored_scale * stored[i];
    squared += d * d;
  }
  return squared;
}

}  // namespace

double HnswGraph::PreciseSquaredDistance(const float* query, uint32_t slot,
                                         float scale) const {
  std::vector<float> buffer;
  const float* stored = options_.int8 ? Row(slot, buffer) : Vector(slot);
  return PreciseSquared(query, scale, stored,
                        options_.scaled ? stored[dimension_] : 1.0, dimension_);
}

std::vector<double> HnswGraph::PreciseSquaredDistances(
    const float* query, std::span<const uint32_t> slots, float scale) const {
  std::vector<double> squared(slots.size());
  VisitRows(slots, [&](size_t i, const float* stored) {
    squared[i] =
        PreciseSquared(query, scale, stored,
                       options_.scaled ? stored[dimension_] : 1.0, dimension_);
  });
  return squared;
}

void HnswGraph::CopyVectors(std::span<const uint32_t> slots,
                            std::span<float* const> out) const {
  VisitRows(slots, [&](size_t i, const float* stored) {
    std::copy(stored, stored + dimension_, out[i]);
  });
}

void HnswGraph::VisitRows(
    std::span<const uint32_t> slots,
    const std::function<void(size_t, const float*)>& visit) const {
  std::vector<uint32_t> away;  // int8 rows not in memory, and where they go
  std::vector<size_t> at;
  for (size_t i = 0; i < slots.size(); ++i) {
    if (!options_.int8) {
      visit(i, Vector(slots[i]));
      continue;
    }
    if (slots[i] >= next_slot_) throw std::out_of_range("no such slot");
    if (const float* row = impl_->rows->Find(slots[i])) {
      visit(i, row);
    } else {
      away.push_back(slots[i]);
      at.push_back(i);
    }
  }
  if (away.empty()) return;
  const size_t stride = dimension_ + 1;
  std::vector<float> rows(away.size() * stride);
  impl_->rows->Gather(away, rows.data());
  for (size_t k = 0; k < away.size(); ++k) visit(at[k], &rows[k * stride]);
}

void HnswGraph::ScanPrecise(
    const float* query, float scale,
    const std::function<bool(uint32_t)>& wanted,
    const std::function<void(uint32_t, double)>& visit) const {
  const size_t stride = dimension_ + 1;
  std::vector<float> chunk;
  for (size_t first = 0; first < next_slot_; first += kFloatChunk) {
    const size_t count = std::min<size_t>(kFloatChunk, next_slot_ - first);
    // int8 rows not in memory: the chunk's rows in one read.
    const bool copied = options_.int8 && impl_->rows->Find(first) == nullptr;
    if (copied) {
      chunk.resize(count * stride);
      impl_->rows->Read(first, count, chunk.data());
    }
    for (size_t k = 0; k < count; ++k) {
      const auto slot = static_cast<uint32_t>(first + k);
      if (!contains(slot) || !wanted(slot)) continue;
      if (!options_.int8) {
        visit(slot, PreciseSquaredDistance(query, slot, scale));
        continue;
      }
      const float* row =
          copied ? chunk.data() + k * stride : impl_->rows->Find(slot);
      visit(slot,
            PreciseSquared(query, scale, row, row[dimension_], dimension_));
    }
  }
}

float HnswGraph::Scale(uint32_t slot) const {
  if (!options_.scaled) return 1.0f;
  std::vector<float> buffer;
  return options_.int8 ? Row(slot, buffer)[dimension_]
                       : Vector(slot)[dimension_];
}

float HnswGraph::CopyVector(uint32_t slot, float* out) const {
  std::vector<float> buffer;
  const float* stored = options_.int8 ? Row(slot, buffer) : Vector(slot);
  std::copy(stored, stored + dimension_, out);
  return options_.scaled ? stored[dimension_] : 1.0f;
}

size_t HnswGraph::MemoryBytes() const {
  const auto& hnsw = impl_->hnsw;
  size_t bytes = hnsw.cur_element_count * hnsw.size_data_per_element_;
  for (size_t i = 0; i < hnsw.cur_element_count; ++i) {
    bytes += hnsw.element_levels_[i] * hnsw.size_links_per_element_;
  }
  return bytes + (options_.int8 ? impl_->rows->MemoryBytes() : 0);
}

bool HnswGraph::contains(uint32_t slot) const {
  auto it = impl_->hnsw.label_lookup_.find(slot);
  return it != impl_->hnsw.label_lookup_.end() &&
         !impl_->hnsw.isMarkedDeleted(it->second);
}

const float* HnswGraph::Vector(uint32_t slot) const {
  if (options_.int8) {
    if (slot >= next_slot_) throw std::out_of_range("no such slot");
    return impl_->rows->Find(slot);
  }
  return reinterpret_cast<const float*>(
      impl_->hnsw.getDataByInternalId(impl_->hnsw.label_lookup_.at(slot)));
}

namespace {

// Version and kind of the layout Save writes (each index kind its own, so
// one kind never parses another's bytes).
// GRF3: the scaled flag, and scaled nodes holding their scale and squared
// norm after the vector. GRF4 (int8 graphs only; float graphs are still
// written as GRF3): GRF3 with an int8 flag after the scaled one, int8
// nodes, and the slots' floats after the links. GRF5 (what int8 graphs
// write; GRF4 is still read): GRF4 with the floats self-checked and each
// row's RowCheck (uint32) after them.
constexpr uint32_t kGraphFormat = 0x47524633;        // "GRF3"
constexpr uint32_t kInt8GraphFormat = 0x47524634;    // "GRF4"
constexpr uint32_t kCheckedInt8Format = 0x47524635;  // "GRF5"

bool KnownFormat(uint32_t format) {
  return format == kGraphFormat || format == kInt8GraphFormat ||
         format == kCheckedInt8Format;
}

template <typename Engine>
std::string EngineState(const Engine& engine) {
  std::ostringstream text;
  text << engine;
  return text.str();
}

template <typename Engine>
bool SetEngineState(const std::string& state, Engine* engine) {
  std::istringstream text(state);
  text >> *engine;
  return !text.fail();
}

absl::Status Malformed(absl::string_view what) {
  return absl::DataLossError(absl::StrCat("HNSW graph snapshot: ", what));
}

bool NonNegative(float x) { return std::isfinite(x) && x >= 0.0f; }

// A scaled node's scale and the scaled vector's squared norm are finite and
// not negative (a zero code's scale is 0).
bool ScaleAndNormOk(const char* node, size_t dimension) {
  const auto* values = reinterpret_cast<const float*>(node);
  return NonNegative(values[dimension]) && NonNegative(values[dimension + 1]);
}

// So are an int8 node's step and squared norm.
bool Int8HeaderOk(const char* node) {
  float header[2];
  std::memcpy(header, node, kInt8Header);
  return NonNegative(header[0]) && NonNegative(header[1]);
}

}  // namespace

void HnswGraph::Save(ByteWriter& out) const {
  const auto& hnsw = impl_->hnsw;
  out.Put<uint32_t>(options_.int8 ? kCheckedInt8Format : kGraphFormat);
  out.Put<uint64_t>(dimension_);
  out.Put<uint64_t>(hnsw.M_);
  out.Put<uint64_t>(hnsw.ef_construction_);
  out.Put<uint8_t>(options_.scaled ? 1 : 0);
  if (options_.int8) out.Put<uint8_t>(1);
  out.Put<uint32_t>(next_slot_);
  out.Put<uint64_t>(free_slots_.size());
  out.PutBytes(free_slots_.data(), free_slots_.size() * sizeof(uint32_t));
  out.PutString(EngineState(hnsw.level_generator_));
  out.PutString(EngineState(hnsw.update_probability_generator_));
  const uint64_t count = hnsw.cur_element_count;
  out.Put<uint64_t>(count);
  out.Put<int32_t>(hnsw.maxlevel_);
  out.Put<uint32_t>(hnsw.enterpoint_node_);
  out.PutBytes(hnsw.data_level0_memory_, count * hnsw.size_data_per_element_);
  for (size_t i = 0; i < count; ++i) {
    const int32_t level = hnsw.element_levels_[i];
    out.Put<int32_t>(level);
    if (level > 0) {
      out.PutBytes(hnsw.linkLists_[i], level * hnsw.size_links_per_element_);
    }
  }
  if (!options_.int8) return;
  impl_->saved.reset();
  const uint64_t floats_at =
      out.file() != nullptr ? out.file()->offset + out.written() : 0;
  const size_t stride = dimension_ + 1;
  std::vector<float> chunk;
  std::vector<uint32_t> checks(count);
  for (size_t first = 0; first < count; first += kFloatChunk) {
    const size_t rows = std::min(kFloatChunk, count - first);
    chunk.resize(rows * stride);
    impl_->rows->Read(first, rows, chunk.data());
    for (size_t k = 0; k < rows; ++k) {
      checks[first + k] = RowCheck({chunk.data() + k * stride, stride});
    }
    out.PutSelfCheckedBytes(chunk.data(), chunk.size() * sizeof(float));
  }
  out.PutBytes(checks.data(), checks.size() * sizeof(uint32_t));
  if (out.file() != nullptr) {
    impl_->saved = Impl::SavedFloats{.file = *out.file(),
                                     .offset = floats_at,
                                     .rows = count,
                                     .written_since = {},
                                     .checks = std::move(checks)};
  }
}

absl::StatusOr<std::unique_ptr<HnswGraph>> HnswGraph::Load(
    size_t dimension, HnswGraphOptions options, ByteReader& in) {
  try {
    return LoadOrThrow(dimension, options, in);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError(
        "out of memory while loading an HNSW graph");
  } catch (const std::exception& e) {
    return absl::ResourceExhaustedError(
        absl::StrCat("loading an HNSW graph: ", e.what()));
  }
}

absl::Status HnswGraph::CheckLoaded(uint32_t count) {
  auto& hnsw = impl_->hnsw;
  // Every link must name an element, every slot must be held once, and
  // the removed slots must be the nodes marked deleted.
  absl::flat_hash_set<uint32_t> removed(free_slots_.begin(), free_slots_.end());
  if (removed.size() != free_slots_.size() ||
      std::any_of(removed.begin(), removed.end(),
                  [&](uint32_t slot) { return slot >= count; })) {
    return Malformed("bad removed slots");
  }
  hnsw.label_lookup_.reserve(count);
  auto links_ok = [&](hnswlib::linklistsizeint* list, size_t most) {
    const size_t size = hnsw.getListCount(list);
    const auto* neighbors = reinterpret_cast<const uint32_t*>(list + 1);
    return size <= most && std::all_of(neighbors, neighbors + size,
                                       [&](uint32_t n) { return n < count; });
  };
  for (uint32_t i = 0; i < count; ++i) {
    const hnswlib::labeltype slot = hnsw.getExternalLabel(i);
    if (slot >= count || !hnsw.label_lookup_.emplace(slot, i).second) {
      return Malformed(absl::StrCat("bad slot of element ", i));
    }
    if (hnsw.isMarkedDeleted(i) != removed.contains(slot)) {
      return Malformed(absl::StrCat("slot ", slot, " removed inconsistently"));
    }
    if (!links_ok(hnsw.get_linklist0(i), hnsw.maxM0_)) {
      return Malformed(absl::StrCat("bad links of element ", i));
    }
    for (int level = 1; level <= hnsw.element_levels_[i]; ++level) {
      if (!links_ok(hnsw.get_linklist(i, level), hnsw.maxM_)) {
        return Malformed(absl::StrCat("bad links of element ", i));
      }
    }
    if (hnsw.isMarkedDeleted(i)) continue;
    // (int8 graphs' scales: checked by LoadFloats, with their rows.)
    const bool sound =
        options_.int8 ? Int8HeaderOk(hnsw.getDataByInternalId(i))
        : options_.scaled
            ? ScaleAndNormOk(hnsw.getDataByInternalId(i), dimension_)
            : true;
    if (!sound) {
      return Malformed(absl::StrCat("bad scale or norm of element ", i));
    }
  }
  return absl::OkStatus();
}

absl::Status HnswGraph::LoadFloats(ByteReader& in, size_t count,
                                   bool with_checks) {
  const size_t stride = dimension_ + 1;
  std::span<const char> bytes, check_bytes;
  if (in.remaining() / (stride * sizeof(float)) < count ||
      !in.GetSpan(count * stride * sizeof(float), &bytes) ||
      (with_checks && !in.GetSpan(count * sizeof(uint32_t), &check_bytes))) {
    return Malformed("truncated floats");
  }
  std::vector<uint32_t> checks(with_checks ? count : 0);
  if (with_checks) {
    std::memcpy(checks.data(), check_bytes.data(), check_bytes.size());
  }
  // Rows with their checks are adopted unread: each is checked when it is
  // read. (Their scales, checked when each row came in and covered by its
  // check since, are not checked again.)
  if (with_checks && in.file() != nullptr &&
      impl_->rows->Adopt(*in.file(), in.FileOffset(bytes), count, {}, checks)) {
    return absl::OkStatus();
  }
  // Every slot's scale, a removed one's too (its floats were written).
  auto row_ok = [&](size_t row) -> absl::Status {
    const char* at = bytes.data() + row * stride * sizeof(float);
    float scale;
    std::memcpy(&scale, at + dimension_ * sizeof(float), sizeof(float));
    if (!NonNegative(scale)) {
      return Malformed(absl::StrCat("bad scale or norm of slot ", row));
    }
    return absl::OkStatus();
  };
  if (!with_checks) {
    for (size_t row = 0; row < count; ++row) {
      if (absl::Status ok = row_ok(row); !ok.ok()) return ok;
    }
    if (in.file() != nullptr &&
        impl_->rows->Adopt(*in.file(), in.FileOffset(bytes), count, {}, {})) {
      return absl::OkStatus();
    }
  }
  impl_->rows->Reserve(count);
  std::vector<float> chunk;
  for (size_t first = 0; first < count; first += kFloatChunk) {
    const size_t rows = std::min(kFloatChunk, count - first);
    chunk.resize(rows * stride);
    std::memcpy(chunk.data(), bytes.data() + first * stride * sizeof(float),
                chunk.size() * sizeof(float));
    for (size_t k = 0; with_checks && k < rows; ++k) {
      if (RowCheck({chunk.data() + k * stride, stride}) != checks[first + k]) {
        return Malformed(absl::StrCat("the floats of slot ", first + k,
                                      " fail their checksum"));
      }
      if (absl::Status ok = row_ok(first + k); !ok.ok()) return ok;
    }
    impl_->rows->Write(first, rows, chunk.data());
  }
  return absl::OkStatus();
}

bool HnswGraph::AdoptSavedFloats() {
  if (!impl_->saved) return false;
  Impl::SavedFloats saved = *std::move(impl_->saved);
  impl_->saved.reset();
  // Rows written since the Save read them stay the rows' own. (New slots'
  // rows are past the saved ones: not adopted.)
  std::sort(saved.written_since.begin(), saved.written_since.end());
  saved.written_since.erase(
      std::unique(saved.written_since.begin(), saved.written_since.end()),
      saved.written_since.end());
  return impl_->rows->Adopt(saved.file, saved.offset, saved.rows,
                            saved.written_since, saved.checks);
}

absl::StatusOr<std::unique_ptr<HnswGraph>> HnswGraph::LoadOrThrow(
    size_t dimension, HnswGraphOptions options, ByteReader& in) {
  uint32_t format = 0;
  uint64_t saved_dimension = 0, m = 0, ef_construction = 0, free_count = 0;
  uint8_t scaled = 0, int8 = 0;
  if (!in.Get(&format) || !KnownFormat(format)) {
    return Malformed("unknown format");
  }
  if (!in.Get(&saved_dimension) || !in.Get(&m) || !in.Get(&ef_construction) ||
      !in.Get(&scaled) || (format != kGraphFormat && !in.Get(&int8))) {
    return Malformed("truncated header");
  }
  auto graph = std::make_unique<HnswGraph>(dimension, options);
  auto& hnsw = graph->impl_->hnsw;
  const HnswGraphOptions& own = graph->options_;  // int8 implies scaled
  if (saved_dimension != dimension || m != hnsw.M_ ||
      ef_construction != hnsw.ef_construction_ || (scaled != 0) != own.scaled ||
      (int8 != 0) != own.int8) {
    return Malformed(absl::StrCat(
        "built with dimension ", saved_dimension, ", m ", m,
        ", ef_construction ", ef_construction, ", scaled ", scaled != 0,
        ", int8 ", int8 != 0, "; this graph has ", dimension, ", ", hnsw.M_,
        ", ", hnsw.ef_construction_, ", ", own.scaled, ", ", own.int8));
  }
  if (!in.Get(&graph->next_slot_) || !in.Get(&free_count) ||
      free_count > graph->next_slot_) {
    return Malformed("bad slot counts");
  }
  graph->free_slots_.resize(free_count);
  std::string level_state, update_state;
  uint64_t count = 0;
  int32_t max_level = 0;
  uint32_t entry = 0;
  if (!in.GetBytes(graph->free_slots_.data(), free_count * sizeof(uint32_t)) ||
      !in.GetString(&level_state, 64) || !in.GetString(&update_state, 64) ||
      !SetEngineState(level_state, &hnsw.level_generator_) ||
      !SetEngineState(update_state, &hnsw.update_probability_generator_) ||
      !in.Get(&count) || !in.Get(&max_level) || !in.Get(&entry)) {
    return Malformed("truncated header");
  }
  const size_t element_bytes = hnsw.size_data_per_element_;
  if (count != graph->next_slot_ || count > in.remaining() / element_bytes ||
      (count == 0) != (max_level < 0) || (count > 0 && entry >= count)) {
    return Malformed("bad element count or entry point");
  }
  {
    graph->Reserve(count);
    in.GetBytes(hnsw.data_level0_memory_, count * element_bytes);
    hnsw.cur_element_count = count;  // element_levels_ are 0 until read
    hnsw.maxlevel_ = max_level;
    hnsw.enterpoint_node_ = entry;
    for (size_t i = 0; i < count; ++i) {
      int32_t level = 0;
      if (!in.Get(&level) || level < 0 || level > max_level) {
        return Malformed(absl::StrCat("bad level of element ", i));
      }
      if (level == 0) continue;
      const size_t bytes = level * hnsw.size_links_per_element_;
      if (in.remaining() < bytes) return Malformed("truncated links");
      hnsw.linkLists_[i] = static_cast<char*>(malloc(bytes));
      if (hnsw.linkLists_[i] == nullptr) throw std::bad_alloc();
      in.GetBytes(hnsw.linkLists_[i], bytes);
      hnsw.element_levels_[i] = level;
    }
    if (count > 0 && hnsw.element_levels_[entry] != max_level) {
      return Malformed("the entry point is not on the top level");
    }
    absl::Status floats =
        own.int8 ? graph->LoadFloats(in, count, format == kCheckedInt8Format)
                 : absl::OkStatus();
    if (!floats.ok()) return floats;
    if (absl::Status checked = graph->CheckLoaded(count); !checked.ok()) {
      return checked;
    }
    hnsw.num_deleted_ = free_count;
  }
  graph->live_ = count - free_count;
  return graph;
}

}  // namespace fleetmem::core
