#include "services/index/exact_index.h"

#include <Eigen/Core>
#if defined(__SSE__)
#include <xmmintrin.h>
#endif

#include <algorithm>
#include <cfloat>
#include <cmath>
#include <limits>
#include <new>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/strings/str_cat.h"
#include "services/core/feature_space.h"
#include "services/index/index_input.h"

namespace fleetmem::index {
namespace {

using engine::Neighbor;
using engine::SearchParams;

// scores[c] = squared_norms[c] - 2 * query_scale * scales[c] * <column c,
// query> + query_norm for the first `count` columns of `vectors` (dimension ×
// count, column-major), in one pass: one column at a time with four SSE
// accumulators, prefetching about 8 KiB ahead (the hardware prefetcher alone
// leaves a third of the bandwidth unused). The summation order differs from a
// sequential sum, which the error bound in Search covers (it holds for any
// order).
void StreamScores(const float* vectors, size_t dimension, size_t count,
                  const float* query, const float* squared_norms,
                  const float* scales, float query_scale, float query_norm,
                  float* scores) {
  const size_t column_bytes = dimension * sizeof(float);
  const size_t ahead =
      std::max<size_t>(1, 8192 / std::max<size_t>(column_bytes, 1));
  for (size_t c = 0; c < count; ++c) {
    const float* v = vectors + c * dimension;
    size_t i = 0;
    float dot = 0.0f;
#if defined(__SSE__)
    if (c + ahead < count) {
      const char* next = reinterpret_cast<const char*>(v + ahead * dimension);
      for (size_t b = 0; b < column_bytes; b += 64) {
        _mm_prefetch(next + b, _MM_HINT_T0);
      }
    }
    __m128 a0 = _mm_setzero_ps(), a1 = a0, a2 = a0, a3 = a0;
    for (; i + 16 <= dimension; i += 16) {
      a0 = _mm_add_ps(a0,
                      _mm_mul_ps(_mm_loadu_ps(v + i), _mm_loadu_ps(query + i)));
      a1 = _mm_add_ps(
          a1, _mm_mul_ps(_mm_loadu_ps(v + i + 4), _mm_loadu_ps(query + i + 4)));
      a2 = _mm_add_ps(
          a2, _mm_mul_ps(_mm_loadu_ps(v + i + 8), _mm_loadu_ps(query + i + 8)));
      a3 = _mm_add_ps(a3, _mm_mul_ps(_mm_loadu_ps(v + i + 12),
                                     _mm_loadu_ps(query + i + 12)));
    }
    for (; i + 4 <= dimension; i += 4) {
      a0 = _mm_add_ps(a0,
                      _mm_mul_ps(_mm_loadu_ps(v + i), _mm_loadu_ps(query + i)));
    }
    float lanes[4];
    _mm_storeu_ps(lanes, _mm_add_ps(_mm_add_ps(a0, a1), _mm_add_ps(a2, a3)));
    dot = (lanes[0] + lanes[1]) + (lanes[2] + lanes[3]);
#endif
    for (; i < dimension; ++i) dot += v[i] * query[i];
    scores[c] = squared_norms[c] - (2.0f * query_scale) * (scales[c] * dot) +
                query_norm;
  }
}

// The columns whose score is within `slack` of the k-th smallest accepted
// score (every column accepted, when fewer than k are): with `slack` twice
// the scores' error bound, a superset of the true k nearest. The k-th
// smallest in one pass with a bounded max-heap (O(size log k); no
// per-vector allocation).
std::vector<size_t> Candidates(const Eigen::VectorXf& scores, double slack,
                               const SearchParams& params,
                               const std::vector<uint64_t>& ids) {
  const size_t count = ids.size();
  std::vector<float> heap;
  heap.reserve(params.k + 1);
  for (size_t column = 0; column < count; ++column) {
    const float score = scores(column);
    if (heap.size() == params.k && score >= heap.front()) continue;
    if (params.accept && !params.accept(ids[column])) continue;
    heap.push_back(score);
    std::push_heap(heap.begin(), heap.end());
    if (heap.size() > params.k) {
      std::pop_heap(heap.begin(), heap.end());
      heap.pop_back();
    }
  }
  if (heap.empty()) return {};
  const double limit = heap.size() < params.k
                           ? std::numeric_limits<double>::infinity()
                           : heap.front() + slack;
  std::vector<size_t> candidates;
  for (size_t column = 0; column < count; ++column) {
    if (scores(column) <= limit &&
        (!params.accept || params.accept(ids[column]))) {
      candidates.push_back(column);
    }
  }
  return candidates;
}

class ExactIndex final : public engine::PlaceIndex {
 public:
  ExactIndex(size_t dimension, ExactIndexOptions options)
      : dimension_(dimension), options_(options) {}

  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override {
    return Store(ids, vectors, /*normalize=*/false);
  }
  absl::Status AddNormalized(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) override {
    return Store(ids, codes, /*normalize=*/true);
  }
  absl::Status Remove(std::span<const uint64_t> ids) override;
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override;
  size_t size() const override { return ids_.size(); }
  size_t dimension() const override { return dimension_; }
  bool HoldsCode(uint64_t id) const override { return column_of_.contains(id); }
  bool CopyCode(uint64_t id, std::vector<float>* code) const override {
    auto it = column_of_.find(id);
    if (it == column_of_.end()) return false;
    const float* stored = vectors_.col(it->second).data();
    code->assign(stored, stored + dimension_);
    return true;
  }
  absl::Status Save(core::ByteWriter& out) const override;
  absl::Status Load(core::ByteReader& in) override;

  void ForEach(
      const std::function<void(uint64_t, std::span<const float>, float)>& visit,
      size_t begin, size_t end) const {
    for (size_t column = begin; column < std::min(end, ids_.size()); ++column) {
      visit(ids_[column],
            std::span<const float>(vectors_.col(column).data(), dimension_),
            scales_(column));
    }
  }

 private:
  // Add; with `normalize` each code is kept as given with the scale that
  // makes it unit length (core::UnitScale).
  template <typename Vector>
  absl::Status Store(std::span<const uint64_t> ids,
                     std::span<const Vector> vectors, bool normalize);
  // Grows the storage to hold `count` vectors (doubling); may throw
  // std::bad_alloc and then leaves the stored vectors unchanged.
  void Reserve(size_t count);
  // Moves the stored vectors into storage for `capacity` (>= size()); may
  // throw std::bad_alloc and then leaves them where they are.
  void Reallocate(size_t capacity);
  // Returns storage once less than a quarter of it is used (a tiered
  // index's tail after the graph took its vectors: 1 GB at 1,000,000 256-d
  // codes). Keeps room for twice the vectors held.
  void MaybeShrink();
  // (Re)computes the squared norm of the scaled column.
  void SetSquaredNorm(size_t column);
  // Squared Euclidean distance of scaled column `column` to `query`, in
  // double.
  double ExactSquaredDistance(size_t column,
                              const Eigen::Map<const Eigen::VectorXf>& query,
                              float query_scale) const;

  const size_t dimension_;
  const ExactIndexOptions options_;
  // dimension_ × capacity; the first size() columns are the stored vectors,
  // as given. Column c stands for scales_(c) times itself: 1 for Add, the
  // inverse norm for AddNormalized, so that a code is held once, as
  // uploaded, and searched as a unit vector.
  Eigen::MatrixXf vectors_;
  Eigen::VectorXf scales_;
  // Squared norm of each scaled column (same capacity).
  Eigen::VectorXf squared_norms_;
  // Column → id; its size is the number of stored vectors.
  std::vector<uint64_t> ids_;
  // Id → column.
  absl::flat_hash_map<uint64_t, size_t> column_of_;
};

void ExactIndex::Reserve(size_t count) {
  const size_t capacity = static_cast<size_t>(vectors_.cols());
  if (count <= capacity) return;
  Reallocate(std::max<size_t>({count, 2 * capacity, 16}));
}

void ExactIndex::Reallocate(size_t capacity) {
  Eigen::MatrixXf vectors(dimension_, capacity);
  Eigen::VectorXf scales(capacity);
  Eigen::VectorXf squared_norms(capacity);
  const size_t used = ids_.size();
  vectors.leftCols(used) = vectors_.leftCols(used);
  scales.head(used) = scales_.head(used);
  squared_norms.head(used) = squared_norms_.head(used);
  vectors_.swap(vectors);
  scales_.swap(scales);
  squared_norms_.swap(squared_norms);
}

template <typename Vector>
absl::Status ExactIndex::Store(std::span<const uint64_t> ids,
                               std::span<const Vector> vectors,
                               bool normalize) {
  if (absl::Status status = CheckAddBatch(
          dimension_, ids, vectors,
          [this](uint64_t id) { return column_of_.contains(id); });
      !status.ok()) {
    return status;
  }
  try {
    Reserve(ids_.size() + ids.size());
    ReserveGeometric(ids_, ids_.size() + ids.size());
    column_of_.reserve(ids_.size() + ids.size());
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("exact index: out of memory in Add");
  }
  for (size_t i = 0; i < ids.size(); ++i) {
    const size_t column = ids_.size();
    const std::span<const float> vector(vectors[i]);
    vectors_.col(column) =
        Eigen::Map<const Eigen::VectorXf>(vector.data(), dimension_);
    scales_(column) = normalize ? core::UnitScale(vector) : 1.0f;
    SetSquaredNorm(column);
    ids_.push_back(ids[i]);
    column_of_.emplace(ids[i], column);
  }
  return absl::OkStatus();
}

void ExactIndex::SetSquaredNorm(size_t column) {
  const float scale = scales_(column);
  squared_norms_(column) =
      scale == 1.0f
          ? vectors_.col(column).squaredNorm()
          : static_cast<float>(core::ScaledSquaredNorm(
                std::span<const float>(vectors_.col(column).data(), dimension_),
                scale));
}

// Version and kind of the layout Save writes (each index kind its own, so
// one kind never parses another's bytes). EXC2 added the scales.
constexpr uint32_t kExactFormat = 0x45584332;  // "EXC2"

absl::Status ExactIndex::Save(core::ByteWriter& out) const {
  out.Put<uint32_t>(kExactFormat);
  out.Put<uint64_t>(dimension_);
  out.Put<uint64_t>(ids_.size());
  out.PutBytes(ids_.data(), ids_.size() * sizeof(uint64_t));
  out.PutBytes(scales_.data(), ids_.size() * sizeof(float));
  // The first size() columns are contiguous.
  out.PutBytes(vectors_.data(), ids_.size() * dimension_ * sizeof(float));
  return absl::OkStatus();
}

absl::Status ExactIndex::Load(core::ByteReader& in) {
  if (!ids_.empty()) {
    return absl::FailedPreconditionError("exact index: Load into a used index");
  }
  uint32_t format = 0;
  uint64_t dimension = 0, count = 0;
  if (!in.Get(&format) || format != kExactFormat) {
    return absl::DataLossError("not an exact index's snapshot");
  }
  if (!in.Get(&dimension) || dimension != dimension_ || !in.Get(&count) ||
      count > in.remaining() /
                  (sizeof(uint64_t) + (dimension_ + 1) * sizeof(float))) {
    return absl::DataLossError(
        absl::StrCat("exact index snapshot: bad header (dimension ", dimension,
                     ", this index ", dimension_, ")"));
  }
  try {
    Reserve(count);
    ids_.resize(count);
    column_of_.reserve(count);
  } catch (const std::bad_alloc&) {
    ids_.clear();
    return absl::ResourceExhaustedError("exact index: out of memory in Load");
  }
  in.GetBytes(ids_.data(), count * sizeof(uint64_t));
  in.GetBytes(scales_.data(), count * sizeof(float));
  in.GetBytes(vectors_.data(), count * dimension_ * sizeof(float));
  for (size_t column = 0; column < count; ++column) {
    SetSquaredNorm(column);
    if (!std::isfinite(squared_norms_(column)) ||
        !std::isfinite(scales_(column)) || scales_(column) < 0.0f ||
        !column_of_.emplace(ids_[column], column).second) {
      ids_.clear();
      column_of_.clear();
      return absl::DataLossError(absl::StrCat(
          "exact index snapshot: bad vector or repeated id at ", column));
    }
  }
  return absl::OkStatus();
}

absl::Status ExactIndex::Remove(std::span<const uint64_t> ids) {
  for (uint64_t id : ids) {
    auto it = column_of_.find(id);
    if (it == column_of_.end()) continue;
    const size_t column = it->second;
    const size_t last = ids_.size() - 1;
    column_of_.erase(it);
    if (column != last) {
      vectors_.col(column) = vectors_.col(last);
      scales_(column) = scales_(last);
      squared_norms_(column) = squared_norms_(last);
      ids_[column] = ids_[last];
      column_of_[ids_[column]] = column;
    }
    ids_.pop_back();
  }
  MaybeShrink();
  return absl::OkStatus();
}

void ExactIndex::MaybeShrink() {
  const size_t capacity = static_cast<size_t>(vectors_.cols());
  const size_t used = ids_.size();
  if (capacity < 1024 || used >= capacity / 4) return;
  try {
    Reallocate(std::max<size_t>(2 * used, 16));
    ids_.shrink_to_fit();
    column_of_.rehash(0);  // to the size held
  } catch (const std::bad_alloc&) {
    // Keeps the larger storage: correct, only not returned yet.
  }
}

double ExactIndex::ExactSquaredDistance(
    size_t column, const Eigen::Map<const Eigen::VectorXf>& query,
    float query_scale) const {
  return (vectors_.col(column).cast<double>() * double{scales_(column)} -
          query.cast<double>() * double{query_scale})
      .squaredNorm();
}

absl::StatusOr<std::vector<Neighbor>> ExactIndex::Search(
    std::span<const float> query, const SearchParams& params) const {
  if (absl::Status status = CheckQuery(dimension_, query); !status.ok()) {
    return status;
  }
  const size_t count = ids_.size();
  if (count == 0 || params.k == 0) return std::vector<Neighbor>();
  try {
    const Eigen::Map<const Eigen::VectorXf> q(query.data(), dimension_);
    // A unit query is scored as query_scale times the query.
    const float query_scale = params.unit_query ? core::UnitScale(query) : 1.0f;
    const float query_norm =
        query_scale == 1.0f
            ? q.squaredNorm()
            : static_cast<float>(core::ScaledSquaredNorm(query, query_scale));
    // Squared distances up to float rounding, in one pass over the vectors.
    Eigen::VectorXf scores(count);
    if (count * dimension_ * sizeof(float) < options_.streaming_scan_bytes) {
      scores.noalias() = vectors_.leftCols(count).transpose() * q;
      scores = (squared_norms_.head(count).array() -
                (2.0f * query_scale) *
                    (scales_.head(count).array() * scores.array())) +
               query_norm;
    } else {
      StreamScores(vectors_.data(), dimension_, count, query.data(),
                   squared_norms_.data(), scales_.data(), query_scale,
                   query_norm, scores.data());
    }

    // Each score is within `bound` of the true squared distance (of the
    // scaled vector), so every true k-nearest vector scores at most kth + 2
    // * bound. Twice the textbook bound on the float dot-product, its
    // scalings and the sum's errors: the dot product's error is at most
    // gamma |x| |q|, and times the scales gamma |scaled x| |scaled q|.
    const double unit = dimension_ * static_cast<double>(FLT_EPSILON);
    const double gamma = unit / (1.0 - unit);
    const double bound = 2.0 * (2.0 * gamma + 8.0 * FLT_EPSILON) *
                         (squared_norms_.head(count).maxCoeff() + query_norm);
    const std::vector<size_t> candidates =
        Candidates(scores, 2.0 * bound, params, ids_);
    if (candidates.empty()) return std::vector<Neighbor>();

    std::vector<std::pair<double, uint64_t>> exact;
    exact.reserve(candidates.size());
    for (size_t column : candidates) {
      exact.emplace_back(ExactSquaredDistance(column, q, query_scale),
                         ids_[column]);
    }
    const size_t wanted = std::min(params.k, exact.size());
    std::partial_sort(exact.begin(), exact.begin() + wanted, exact.end());
    std::vector<Neighbor> neighbors;
    neighbors.reserve(wanted);
    for (size_t i = 0; i < wanted; ++i) {
      neighbors.push_back(
          {exact[i].second,
           static_cast<float>(std::sqrt(std::max(0.0, exact[i].first)))});
    }
    return neighbors;
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("exact index: out of memory in Search");
  }
}

}  // namespace

void ForEachExactVector(
    const engine::PlaceIndex& index,
    const std::function<void(uint64_t, std::span<const float>, float)>& visit,
    size_t begin, size_t end) {
  if (const auto* exact = dynamic_cast<const ExactIndex*>(&index)) {
    exact->ForEach(visit, begin, end);
  }
}

std::unique_ptr<engine::PlaceIndex> NewExactIndex(size_t dimension,
                                                  ExactIndexOptions options) {
  return std::make_unique<ExactIndex>(dimension, options);
}

}  // namespace fleetmem::index
