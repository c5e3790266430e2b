// Approximate nearest-neighbour search with FLANN randomized kd-trees (L2).
#ifndef FLEETMEM_SERVICES_INDEX_FLANN_INDEX_H_
#define FLEETMEM_SERVICES_INDEX_FLANN_INDEX_H_

#include <cstddef>
#include <memory>

#include "services/engine/place_index.h"

namespace fleetmem::index {

struct FlannIndexOptions {
  // Randomized kd-trees searched in parallel (FLANN KDTreeIndexParams).
  // More trees: better recall, slower builds, more memory. Values < 1 mean 1.
  int trees = 4;
  // Leaves visited per search (FLANN SearchParams::checks): the
  // recall/latency knob. <= 0 means unlimited: exact search in a single
  // kd-tree (`trees` is then ignored; slower than NewExactIndex).
  int checks = 128;
  // Removed points stay in the trees (skipped by searches) until they exceed
  // this fraction of the live points; then the trees are rebuilt from the
  // live points only.
  float rebuild_removed_fraction = 0.25f;
  // Added points go into the existing trees until the index has grown to
  // this factor of its size at the last build; then FLANN rebuilds the trees
  // (FLANN addPoints rebuild_threshold). Values <= 1 never rebuild on growth.
  float add_rebuild_factor = 2.0f;
  // With SearchParams::accept, the first FLANN search asks for k times this
  // many neighbours and doubles until k are accepted or all points were
  // returned. Values < 1 mean 1.
  int accept_oversample = 4;
};

// Returns an empty FLANN index for vectors of `dimension` (> 0; with 0 every
// Add is INVALID_ARGUMENT).
//
// Approximate: Search may miss some of the true k nearest (see
// docs/index-benchmark.md for measured recall); the neighbours found come
// nearest first with their Euclidean distance (square root of FLANN's float
// squared L2), ties by the smaller id. Trees are built with std::random_device,
// so two indexes of the same data may answer slightly differently.
//
// The index owns a copy of every vector (FLANN keeps pointers to them).
// Errors from FLANN (exceptions) are caught: INTERNAL, or RESOURCE_EXHAUSTED
// for out of memory; a failed Add adds nothing. Beyond the port's contract,
// Add and Search refuse non-finite values and Add refuses a repeated id in
// the batch or ids.size() != vectors.size() (INVALID_ARGUMENT).
// Thread-safety as in engine::PlaceIndex (concurrent Search calls are safe).
std::unique_ptr<engine::PlaceIndex> NewFlannIndex(
    size_t dimension, const FlannIndexOptions& options = {});

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_FLANN_INDEX_H_
