// Exact nearest-neighbour search by brute force (Eigen): the reference
// PlaceIndex every approximate index is measured against.
#ifndef FLEETMEM_SERVICES_INDEX_EXACT_INDEX_H_
#define FLEETMEM_SERVICES_INDEX_EXACT_INDEX_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>

#include "services/engine/place_index.h"

namespace fleetmem::index {

struct ExactIndexOptions {
  // From this many bytes of stored vectors on, Search scores them with a
  // streaming loop that prefetches ahead instead of Eigen's matrix-vector
  // product. Eigen's kernel is faster while the vectors sit in the cache,
  // the streaming loop beyond it. The default is the 32 MiB L3 of the
  // project's VM: ann_bench measured Eigen's kernel faster at 20 MB and the
  // streaming loop faster at 50 MB (docs/performance.md); 0 streams always,
  // SIZE_MAX never.
  size_t streaming_scan_bytes = size_t{32} << 20;
};

// Returns an empty exact index for vectors of `dimension` (> 0; with 0 every
// Add is INVALID_ARGUMENT).
//
// Vectors are the columns of one contiguous float matrix, as given (a code
// added by AddNormalized is kept as uploaded, with the scale that makes it
// unit length: HoldsCode is true for every stored id); Remove moves the
// last column into the hole (O(dimension) per id). Search scores all stored
// vectors in one pass (‖x‖² − 2xᵀq + ‖q‖²), then
// re-scores in double precision every candidate that float rounding could
// place among the k nearest, so the result is the exact k nearest accepted
// vectors, ties broken by the smaller id. Cost per Search: O(size ×
// dimension) plus one call of params.accept per stored vector when set.
//
// Beyond the port's contract: Add and Search also refuse non-finite values
// (INVALID_ARGUMENT), and Add refuses a batch with a repeated id or with
// ids.size() != vectors.size(). Out of memory is RESOURCE_EXHAUSTED and
// changes nothing. Thread-safety as in engine::PlaceIndex.
std::unique_ptr<engine::PlaceIndex> NewExactIndex(
    size_t dimension, ExactIndexOptions options = {});

// Calls visit(id, vector as given, its scale) for the vectors of an index
// made by NewExactIndex at storage positions [begin, end) (clamped to its
// size), in storage order;
// does nothing for another kind of index. Removing the vectors at the last
// positions moves no other vector.
void ForEachExactVector(
    const engine::PlaceIndex& index,
    const std::function<void(uint64_t, std::span<const float>, float)>& visit,
    size_t begin = 0, size_t end = SIZE_MAX);

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_EXACT_INDEX_H_
