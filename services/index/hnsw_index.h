// Approximate nearest-neighbour search with an HNSW graph (hnswlib, Malkov &
// Yashunin 2018), and the tiered index the server uses by default: exact
// below a size threshold, HNSW from it on.
#ifndef FLEETMEM_SERVICES_INDEX_HNSW_INDEX_H_
#define FLEETMEM_SERVICES_INDEX_HNSW_INDEX_H_

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include "services/engine/place_index.h"

namespace fleetmem::index {

struct HnswIndexOptions {
  // Links per node (2 x m on the base layer).
  size_t m = 16;
  // Candidate list while inserting; larger builds a better graph, slower.
  // 40 is what the 1,000,000-code measurement of docs/performance.md used
  // (recall@10 0.994 at ef_search 128); it inserts ~2x faster than 100.
  size_t ef_construction = 40;
  // Candidate list while searching (at least k is used). 128 gives
  // recall@10 >= 0.95 on 1,000,000 x 256-d codes (docs/performance.md).
  size_t ef_search = 128;
  // Seed of the level generator (a graph built from the same inserts is the
  // same graph with insert_threads = 1).
  uint64_t seed = 42;
  // Share of a removed node's old neighbours whose links are recomputed when
  // its node is reused for a new vector.
  float repair_probability = 0.1f;
  // Threads that link a batch of new vectors into the graph (Add's caller
  // and insert_threads - 1 started for the batch; the tiered index's
  // background steps too). Inserting is bound by memory latency (hnswlib
  // reads each visited neighbour's vector), so two threads insert about
  // twice as fast on the 2-core machine (docs/performance.md). With more
  // than one the links depend on how the threads interleave: the same Adds
  // may build different graphs, and an approximate search may answer
  // differently from run to run (the slots, levels and vectors are the
  // same; what the engine stores never depends on the place index). 1: the
  // same Adds always build the same graph.
  size_t insert_threads = 2;
  // A filtered search (SearchParams::accept) first asks for k x this many
  // candidates, then four times more until k are accepted. A search asking
  // for half the index or more (filtered or not) scans every vector
  // instead.
  size_t accept_oversample = 8;
  // The codes the graph walks on (core::HnswGraphOptions::int8). kFloat:
  // the codes themselves. kInt8: int8 scalar quantization with one scale
  // per code (a quarter of the bytes each distance reads), the floats kept
  // beside for rescoring and for CopyCode; each search asks the graph for
  // rescore_oversample times the candidates it returns and ranks them by
  // the precise distance. kInt8 by default: on 100,000 and 1,000,000 256-d
  // codes it inserted 1.9-2.1x as fast as the float graph (2.4-2.5x
  // hnswlib) and answered 1.9-2.3x the float graph's queries a second at
  // the same recall@10; it holds a quarter more (the floats and the int8
  // nodes; docs/performance.md, "Quantized codes") unless the floats are
  // kept in a file (floats_dir: then 0.28x in process).
  enum class Codes { kFloat, kInt8 };
  Codes codes = Codes::kInt8;
  // kInt8: candidates rescored per neighbour returned.
  size_t rescore_oversample = 4;
  // kInt8: where the floats kept beside the graph live. Empty: on the heap
  // (core::MemoryFloatRows). A directory: in a file of each graph's own
  // there (FileFloatRows, unlinked at once), so that they are the page
  // cache's and the process holds only the int8 nodes; a search then reads
  // its rescore_oversample × k candidates' rows with pread, and CopyCode a
  // row. The graph's snapshot still holds the floats (it is what a restart
  // reads them from).
  std::string floats_dir;
};

// "float" or "int8" (a configuration's words for HnswIndexOptions::Codes);
// nullopt for anything else.
std::optional<HnswIndexOptions::Codes> ParseHnswCodes(std::string_view word);
std::string_view HnswCodesName(HnswIndexOptions::Codes codes);

// An empty HNSW index for vectors of `dimension`. Remove marks the node
// deleted (it still routes searches) and a later Add reuses it, so memory is
// bounded by the most vectors ever held at once. Add costs O(log n)
// distance computations (0.1-1 ms at 256-d on the reference machine,
// docs/performance.md), Search O(ef log n).
// Distances are Euclidean, computed in float. Each node keeps its vector
// as given, with a scale (AddNormalized's codes as uploaded, with the
// inverse of their norm), so HoldsCode is true for every id held and the
// engine needs no copy of its own. Thread-safety as in engine::PlaceIndex
// (concurrent Search calls are safe).
std::unique_ptr<engine::PlaceIndex> NewHnswIndex(size_t dimension,
                                                 HnswIndexOptions options = {});

// Sets ef_search of an index made by NewHnswIndex (or of a tiered index's
// graph, once it has one) without rebuilding it; the caller serialises it
// against Search like a writer. False for any other index.
bool SetHnswEfSearch(engine::PlaceIndex& index, size_t ef_search);

// The bytes the graph of an index made by NewHnswIndex holds for its
// vectors and links (core::HnswGraph::MemoryBytes); 0 for any other. A
// reader. For benchmarks.
size_t HnswMemoryBytes(const engine::PlaceIndex& index);

struct TieredIndexOptions {
  // The exact index serves while fewer vectors than this are held; from this
  // size on an HNSW graph takes them, and below half of it the graph is
  // dropped again. The default is where the exact scan's median query passes
  // 1 ms (the P2 budget over gRPC) on the 2-core reference machine
  // (bench/ann_bench, docs/performance.md).
  size_t hnsw_from = 20'000;
  HnswIndexOptions hnsw;
  // With a graph, Add only appends to an exact "growing" segment (O(dimension)
  // per vector) and one background thread per index moves the vectors into
  // the graph, a few at a time; Search scans the growing segment beside the
  // graph, so every added vector is found at once. false: Add inserts into
  // the graph itself (slower uploads; the graph then depends only on the
  // calls made).
  bool background = true;
  // Back-pressure: an Add that finds more than this many vectors waiting
  // inserts as many vectors into the graph itself as it adds (a step at a
  // time, as the background thread, letting searches in between), so the
  // growing segment (scanned by every Search) stops growing. A restart's
  // single bulk Add is not held up: the backlog is drained in the background.
  // Every Search scans the waiting vectors exactly (about 0.1 ms per 2,000
  // 256-d codes on an idle machine). A burst is absorbed by the write
  // path's log (engine::WritePath), not by this segment, so it stays small
  // (it was 20,000 before that log existed; docs/performance.md).
  size_t max_unindexed = 2'000;
  // Vectors moved into the graph per step and insert thread (the
  // background thread's and back-pressure's steps; hnsw.insert_threads
  // link a step's vectors) under the index's writer lock. A Search waits
  // for at most one step (0.3-1 ms for one float insert per thread at
  // 256-d here); between steps every waiting caller goes first. 0 (the
  // default): 2 with int8 codes, whose inserts take about half a float
  // insert's time, so that a step takes as long as a float step of 1 (it
  // was 4, then 1: a query beside a drain of the write backlog waits for
  // fewer inserts); a step's fixed cost (its staging, a helper thread, the
  // lock's hand-overs) made 2 apply uploads 1.4-1.5x as fast as 1 at
  // 100,000 held (docs/performance.md, "Quantized codes").
  size_t indexer_batch = 0;
  // The background thread's nice value (0..19; common::MarkBackgroundThread,
  // as the write path's appliers): the threads answering calls get the
  // larger CPU share while it catches up. 0: theirs.
  int indexer_nice = 10;
};

// Exact below options.hnsw_from vectors, HNSW (plus the growing segment)
// from it on. unindexed() is the growing segment's size while there is a
// graph (0 before). Thread-safe: Add/Remove/Search may be called from any
// thread (the engine still serialises writers); Search calls run concurrently
// with each other.
std::unique_ptr<engine::PlaceIndex> NewTieredIndex(
    size_t dimension, TieredIndexOptions options = {});

// Blocks until a tiered index has no vector waiting for its graph (or its
// background thread stopped on an error); returns the number still waiting.
// Immediate for any other index. For benchmarks, tests and shutdown.
size_t WaitForIndexing(engine::PlaceIndex& index);

}  // namespace fleetmem::index

#endif  // FLEETMEM_SERVICES_INDEX_HNSW_INDEX_H_
