// Input checks and a growth rule shared by the PlaceIndex implementations
// of this module (internal to services/index; not part of the engine's
// port).
#ifndef FLEETMEM_SERVICES_INDEX_INDEX_INPUT_H_
#define FLEETMEM_SERVICES_INDEX_INDEX_INPUT_H_

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <span>
#include <vector>

#include "absl/status/status.h"

namespace fleetmem::index {

// Checks an Add batch before anything is stored: a dimension > 0, as many
// ids as vectors, every vector of `dimension` with finite values, no id
// repeated in the batch and no id for which `is_stored` returns true. Every
// error is INVALID_ARGUMENT naming the offending position and id.
absl::Status CheckAddBatch(size_t dimension, std::span<const uint64_t> ids,
                           std::span<const std::vector<float>> vectors,
                           const std::function<bool(uint64_t)>& is_stored);
absl::Status CheckAddBatch(size_t dimension, std::span<const uint64_t> ids,
                           std::span<const std::span<const float>> vectors,
                           const std::function<bool(uint64_t)>& is_stored);

// A query must have `dimension` finite values; INVALID_ARGUMENT otherwise.
absl::Status CheckQuery(size_t dimension, std::span<const float> query);

// Makes room for `needed` elements, at least doubling the capacity, so that
// a series of Adds copies each element O(1) times (a reserve of exactly
// `needed` copies the whole vector at every Add).
template <typename T>
void ReserveGeometric(std::vector<T>& v, size_t needed) {
  if (needed > v.capacity()) v.reserve(std::max(needed, 2 * v.capacity()));
}

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_INDEX_INPUT_H_
