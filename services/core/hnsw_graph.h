// An HNSW graph (hnswlib; Malkov & Yashunin 2018) over float vectors under
// small integer slots, with removal: a removed slot's node is marked deleted
// (it still routes searches) and the next Add reuses it, so memory stays
// bounded by the most vectors held at once. The one translation unit that
// includes hnswlib (its 0.6 headers define non-inline functions), shared by
// forgetting's ClosestPairTracker and services/index's HNSW place index.
// Deterministic: the same calls give the same graph (Link in order, not
// concurrently). Not thread-safe for writers; concurrent Search calls are
// safe, and SearchBesideLinks may also run beside Link.
#ifndef FLEETMEM_SERVICES_CORE_HNSW_GRAPH_H_
#define FLEETMEM_SERVICES_CORE_HNSW_GRAPH_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "services/core/byte_stream.h"
#include "services/core/float_rows.h"

namespace fleetmem::core {

struct HnswGraphOptions {
  // Links per node (2 x m on the base layer).
  size_t m = 16;
  // Candidate lists while inserting and while searching (at least k is used).
  size_t ef_construction = 40;
  size_t ef_search = 64;
  // Seed of the level generator.
  uint64_t seed = 42;
  // Share of a reused node's old neighbours whose links are recomputed
  // (hnswlib's replace-deleted repairs all of them, at ~30x an insert's cost).
  float repair_probability = 0.1f;
  // Each node stores its vector as given plus a scale factor, and distances
  // are between the scaled vectors (Add's `scale`): a place index keeps a
  // code exactly as uploaded and searches its unit-length version, with
  // one copy. Costs two floats per node (the scale and the scaled squared
  // norm; distances are norms minus twice the dot product). false: plain
  // vectors (hnswlib's L2 space), Add's scale must be 1.
  bool scaled = false;
  // The graph's own copy of each vector, what its distances (while linking
  // and searching) are computed on: false, the floats as above; true
  // (requires `scaled`), int8 scalar quantization of the scaled vector
  // with one scale per vector (max |value| / 127; bench/quantization_choice.py
  // measured it against one scale per dimension) and the quantized
  // vector's squared norm, so that a node is dimension + 8 bytes (a quarter
  // of the floats at 256-d) and a distance is an integer dot product. The
  // floats as given are still kept, beside the nodes (Vector, Scale,
  // PreciseSquaredDistance read them), for rescoring the walk's candidates
  // and for the caller's copies; search answers carry the quantized
  // distances, so a caller rescoring them asks for more than it needs.
  bool int8 = false;
  // With int8: where those floats are kept, a row of dimension + 1 (the
  // vector as given, then its scale) per slot. Empty: MemoryFloatRows, on
  // the heap; services/index's FileFloatRows keeps them in a file (the
  // page cache), read back only to rescore and to copy codes out.
  FloatRowsMaker float_rows;
};

class HnswGraph {
 public:
  HnswGraph(size_t dimension, HnswGraphOptions options);
  ~HnswGraph();
  HnswGraph(const HnswGraph&) = delete;
  HnswGraph& operator=(const HnswGraph&) = delete;
  // hnswlib's state lives behind a pointer, so a move keeps it in place.
  HnswGraph(HnswGraph&&) noexcept;
  HnswGraph& operator=(HnswGraph&&) noexcept;

  // Room for `count` live vectors without reallocation. May throw
  // std::bad_alloc (the graph is unchanged then).
  void Reserve(size_t count);
  // Adds `dimension` floats, standing for `scale` times them (options.scaled;
  // otherwise scale must be 1); returns the slot (a removed one if any, last
  // removed first). May throw std::bad_alloc, or std::system_error when
  // int8 floats kept in a file cannot be written (the graph is unchanged
  // then).
  uint32_t Add(const float* vector, float scale = 1.0f);
  // Insertion in two steps, for linking new nodes on several threads (the
  // caller's: this library starts none). Stage adds vectors[i] standing
  // for scales[i] times it as Add would one after the other: the same
  // slots, levels and stored vectors. It refills removed slots and an empty
  // graph's first node at once (Add itself; `linked` counts them, they come
  // first) and leaves the others staged: stored but not linked, so a Search
  // does not find them yet. May throw std::bad_alloc (or std::system_error:
  // int8 floats kept in a file that cannot grow) before it changes
  // anything; out of memory or failing to write the floats later, it
  // stages nothing more and says so in `complete` (the vectors past
  // `slots` are not added).
  struct Staged {
    std::vector<uint32_t> slots;  // of the vectors added, in order
    size_t linked = 0;            // slots[0, linked) are linked already
    bool complete = true;         // slots holds every vector
  };
  Staged Stage(std::span<const float* const> vectors,
               std::span<const float> scales);
  // Links staged node slots[i] (linked <= i) into the graph. Calls for
  // different i may run concurrently (hnswlib's per-node locks), and so may
  // SearchBesideLinks and the reads of stored vectors (Vector, Scale,
  // contains); no other call may run until every staged node is linked. Linked
  // one after the other in order, the graph is the one the same Adds build;
  // concurrently, the links depend on how the threads interleave, so two runs
  // may build different graphs and an approximate search may answer
  // differently.
  void Link(const Staged& staged, size_t i);
  // Removes a live slot.
  void Remove(uint32_t slot);
  // Up to k nearest live slots to `scale` times `query` (1 unless
  // options.scaled) as (squared Euclidean distance, slot), nearest first
  // (with options.int8, both quantized: the distance and the order are
  // approximate; PreciseSquaredDistance scores them).
  std::vector<std::pair<float, uint32_t>> Search(const float* query, size_t k,
                                                 float scale = 1.0f) const;
  // Search, safe to call while Link calls run (not beside any other
  // writer; hnswlib's own search is not): it reads each node's links under
  // hnswlib's per-node lock and the entry point under its global lock,
  // holding one lock at a time (no deadlock with Link, which never waits
  // for a lock a search holds for long). On a graph that does not change it
  // answers exactly as Search (the same walk); a lock per visited node
  // makes it a little slower. Nodes staged but not linked are not found.
  std::vector<std::pair<float, uint32_t>> SearchBesideLinks(
      const float* query, size_t k, float scale = 1.0f) const;
  // Changes the search candidate list (no rebuild; not while searching).
  void set_ef_search(size_t ef);
  // Squared Euclidean distance between `scale` times `query` and the
  // (scaled) vector of `slot`, in double precision, term by term (exact to
  // rounding, where the scaled graph's own distance loses about 1e-7 to
  // cancellation): for scoring a search's answers. With int8 floats kept
  // in a file, reads the slot's row (std::system_error on an I/O error).
  double PreciseSquaredDistance(const float* query, uint32_t slot,
                                float scale = 1.0f) const;
  // PreciseSquaredDistance of each of `slots` (live), in order: an int8
  // graph's rows not in memory are read in one FloatRows::Gather (a file's
  // rows off the page cache are then read side by side, not one after
  // another). std::system_error on an I/O error.
  std::vector<double> PreciseSquaredDistances(const float* query,
                                              std::span<const uint32_t> slots,
                                              float scale = 1.0f) const;
  // The stored vector of a live slot, as given to Add (unscaled), where it
  // lies in memory; nullptr for an int8 graph whose floats are kept
  // elsewhere (options.float_rows): CopyVector reads them.
  const float* Vector(uint32_t slot) const;
  // Copies the stored vector of a live slot (dimension floats) to `out`
  // and returns its scale (one read of its row); std::system_error when
  // the row cannot be read.
  float CopyVector(uint32_t slot, float* out) const;
  // CopyVector of each of `slots` (live) into out[i], the rows read as
  // PreciseSquaredDistances reads them.
  void CopyVectors(std::span<const uint32_t> slots,
                   std::span<float* const> out) const;
  // visit(slot, PreciseSquaredDistance(query, slot, scale)) for every live
  // slot that `wanted` accepts, in slot order: a scan of the graph's floats,
  // read a chunk of rows at a time where they are not in memory (one read
  // per 4,096 rows, not one per row). std::system_error as CopyVector.
  void ScanPrecise(const float* query, float scale,
                   const std::function<bool(uint32_t)>& wanted,
                   const std::function<void(uint32_t, double)>& visit) const;
  // The scale given with it (1 unless options.scaled); std::system_error
  // as CopyVector.
  float Scale(uint32_t slot) const;

  // The bytes the graph holds for its vectors and links (hnswlib's nodes in
  // use, upper layers and, with options.int8, the floats kept beside them
  // where they are in the process's memory); capacity reserved but not
  // used is not counted.
  size_t MemoryBytes() const;

  // Writes the whole graph (vectors, links, removed slots and the level
  // generator's state) for Load. O(size); the graph is only read, but an
  // int8 graph notes where its floats went when `out` writes to a file
  // (ByteWriter::file), for AdoptSavedFloats: Saves must not overlap. An
  // int8 graph's floats are self-checked bytes (ByteWriter::
  // PutSelfCheckedBytes), each row's RowCheck written after them.
  void Save(ByteWriter& out) const;
  // After the last Save wrote to a file and its bytes are there: an int8
  // graph whose floats no Add has written since reads them from that file
  // from now on (FloatRows::Adopt), and drops its own copy (a file's rows
  // whose disk is then freed). False, changing nothing, otherwise (no such
  // Save, a row written since, rows that keep no file). A writer.
  bool AdoptSavedFloats();
  // A graph equal to the one Save wrote: the same searches give the same
  // results and the same later calls build the same graph. An int8 graph
  // read from a file (ByteReader::file) leaves its floats there when its
  // rows can read them from it (FloatRows::Adopt) rather than copy them;
  // it reads none of them then (each row is checked against its RowCheck
  // when it is read), else each row is checked as it is copied.
  // `dimension`, options.m and options.ef_construction must be those it was
  // built with (options.ef_search may differ). DATA_LOSS names what does not
  // fit (a truncated or inconsistent graph, other build options: every link and
  // slot is checked, so a bad snapshot cannot make a search read out of
  // bounds); RESOURCE_EXHAUSTED when out of memory.
  static absl::StatusOr<std::unique_ptr<HnswGraph>> Load(
      size_t dimension, HnswGraphOptions options, ByteReader& in);
  // True if `slot` holds a vector (added and not removed).
  bool contains(uint32_t slot) const;
  // Slots ever handed out (the live ones and the removed ones).
  uint32_t slot_count() const { return next_slot_; }
  size_t size() const { return live_; }
  size_t dimension() const { return dimension_; }

 private:
  struct Impl;
  // `vector` in the layout the graph's nodes store (with its scale when
  // scaled, quantized when int8); points into `buffer` or at `vector`
  // itself.
  const void* Stored(const float* vector, float scale,
                     std::vector<float>& buffer) const;
  // With options.int8: room for the floats of `slots` slots (may throw
  // std::bad_alloc or std::system_error, keeping what was held).
  void ReserveFloats(size_t slots);
  // With options.int8: keeps `vector` (as given) and `scale` as slot's
  // floats (ReserveFloats first; std::system_error on an I/O error).
  void KeepFloats(uint32_t slot, const float* vector, float scale);
  // With options.int8: slot's row (dimension floats, then the scale) where
  // it lies in memory, or read into `buffer`.
  const float* Row(uint32_t slot, std::vector<float>& buffer) const;
  // visit(i, the stored vector of slots[i] (dimension floats, then the
  // scale with options.scaled)) for each i: rows in memory where they lie,
  // an int8 graph's others gathered into one buffer first.
  void VisitRows(std::span<const uint32_t> slots,
                 const std::function<void(size_t, const float*)>& visit) const;
  // Load without its handlers for hnswlib's exceptions.
  static absl::StatusOr<std::unique_ptr<HnswGraph>> LoadOrThrow(
      size_t dimension, HnswGraphOptions options, ByteReader& in);
  // After a load of `count` elements: every link names an element, every
  // slot is held once (the slot lookup is built here), the removed slots
  // are the nodes marked deleted, and (scaled) every scale and norm is
  // sound.
  absl::Status CheckLoaded(uint32_t count);
  // With options.int8: reads the `count` slots' floats that Save wrote
  // after the links into the graph's rows; DATA_LOSS when they are
  // truncated or a scale is negative or not finite.
  absl::Status LoadFloats(ByteReader& in, size_t count, bool with_checks);
  size_t dimension_;
  HnswGraphOptions options_;
  std::unique_ptr<Impl> impl_;
  std::vector<uint32_t> free_slots_;
  uint32_t next_slot_ = 0;
  size_t live_ = 0;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_HNSW_GRAPH_H_
