// Approximate nearest-neighbour search with an HNSW graph (hnswlib, Malkov &
// Yashunin 2018), and the tiered index the server uses by default: exact
// below a size threshold, HNSW from it on.
#ifndef FLEETMEM_SERVICES_INDEX_HNSW_INDEX_H_
#define FLEETMEM_SERVICES_INDEX_HNSW_INDEX_H_

#include <cstddef>
#include <cstdint>
#include <memory>

#include "services/engine/place_index.h"

namespace fleetmem::index {

struct HnswIndexOptions {
  // Links per node (2 x m on the base layer).
  size_t m = 16;
  // Candidate list while inserting; larger builds a better graph, slower.
  size_t ef_construction = 100;
  // Candidate list while searching (at least k is used). 128 gives
  // recall@10 >= 0.95 on 1,000,000 x 256-d codes (docs/performance.md).
  size_t ef_search = 128;
  // Seed of the level generator (a graph built from the same inserts is the
  // same graph).
  uint64_t seed = 42;
  // Share of a removed node's old neighbours whose links are recomputed when
  // its node is reused for a new vector.
  float repair_probability = 0.1f;
  // A filtered search (SearchParams::accept) first asks for k x this many
  // candidates, then four times more until k are accepted; past half the
  // index it scans every vector instead.
  size_t accept_oversample = 8;
};

// An empty HNSW index for vectors of `dimension`. Remove marks the node
// deleted (it still routes searches) and a later Add reuses it, so memory is
// bounded by the most vectors ever held at once. Add costs O(log n)
// distance computations (0.1-1 ms at 256-d on the reference machine,
// docs/performance.md), Search O(ef log n).
// Distances are Euclidean, computed in float. Thread-safety as in
// engine::PlaceIndex (concurrent Search calls are safe).
std::unique_ptr<engine::PlaceIndex> NewHnswIndex(size_t dimension,
                                                 HnswIndexOptions options = {});

// Sets ef_search of an index made by NewHnswIndex (or of a tiered index's
// graph, once it has one) without rebuilding it; the caller serialises it
// against Search like a writer. False for any other index.
bool SetHnswEfSearch(engine::PlaceIndex& index, size_t ef_search);

struct TieredIndexOptions {
  // The exact index serves while fewer vectors than this are held; the HNSW
  // graph is built from them when the size reaches it, and dropped again
  // below half of it. The default is where the exact scan's median query
  // passes 1 ms (the P2 budget over gRPC) on the 2-core reference machine
  // (bench/ann_bench, docs/performance.md); below it, uploads keep the exact
  // index's O(dimension) insert instead of HNSW's ~0.1-1 ms.
  size_t hnsw_from = 20'000;
  HnswIndexOptions hnsw;
};

std::unique_ptr<engine::PlaceIndex> NewTieredIndex(
    size_t dimension, TieredIndexOptions options = {});

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_HNSW_INDEX_H_
