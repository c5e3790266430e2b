#include "services/index/index_input.h"

#include <cmath>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"

namespace fleetmem::index {
namespace {

bool AllFinite(std::span<const float> values) {
  for (float v : values) {
    if (!std::isfinite(v)) return false;
  }
  return true;
}

template <typename Vector>
absl::Status CheckBatch(size_t dimension, std::span<const uint64_t> ids,
                        std::span<const Vector> vectors,
                        const std::function<bool(uint64_t)>& is_stored) {
  if (ids.size() != vectors.size()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "index add: ", ids.size(), " ids but ", vectors.size(), " vectors"));
  }
  if (dimension == 0) {
    return absl::InvalidArgumentError(
        "index add: an index of dimension 0 cannot hold vectors");
  }
  absl::flat_hash_set<uint64_t> batch;
  batch.reserve(ids.size());
  for (size_t i = 0; i < ids.size(); ++i) {
    if (vectors[i].size() != dimension) {
      return absl::InvalidArgumentError(absl::StrCat(
          "index add: vectors[", i, "] (id ", ids[i], ") has dimension ",
          vectors[i].size(), ", the index has ", dimension));
    }
    if (!AllFinite(std::span<const float>(vectors[i]))) {
      return absl::InvalidArgumentError(
          absl::StrCat("index add: vectors[", i, "] (id ", ids[i],
                       ") has a non-finite value"));
    }
    if (!batch.insert(ids[i]).second) {
      return absl::InvalidArgumentError(absl::StrCat(
          "index add: id ", ids[i], " appears twice in the batch"));
    }
    if (is_stored(ids[i])) {
      return absl::InvalidArgumentError(
          absl::StrCat("index add: id ", ids[i], " is already in the index"));
    }
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status CheckAddBatch(size_t dimension, std::span<const uint64_t> ids,
                           std::span<const std::vector<float>> vectors,
                           const std::function<bool(uint64_t)>& is_stored) {
  return CheckBatch(dimension, ids, vectors, is_stored);
}

absl::Status CheckAddBatch(size_t dimension, std::span<const uint64_t> ids,
                           std::span<const std::span<const float>> vectors,
                           const std::function<bool(uint64_t)>& is_stored) {
  return CheckBatch(dimension, ids, vectors, is_stored);
}

absl::Status CheckQuery(size_t dimension, std::span<const float> query) {
  if (query.size() != dimension) {
    return absl::InvalidArgumentError(
        absl::StrCat("index search: query has dimension ", query.size(),
                     ", the index has ", dimension));
  }
  if (!AllFinite(query)) {
    return absl::InvalidArgumentError(
        "index search: query has a non-finite value");
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::index
