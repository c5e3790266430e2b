// The search port of the engine: nearest codes among the static memory's
// traces. Implementations: services/index (exact brute force with Eigen;
// FLANN randomized kd-trees).
#ifndef FLEETMEM_SERVICES_ENGINE_PLACE_INDEX_H_
#define FLEETMEM_SERVICES_ENGINE_PLACE_INDEX_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "services/core/byte_stream.h"
#include "services/core/feature_space.h"
#include "services/engine/fleet_settings.h"

namespace fleetmem::engine {

struct Neighbor {
  uint64_t id = 0;
  float distance = 0.0f;  // Euclidean, between the stored vectors
};

struct SearchParams {
  // Neighbours wanted.
  size_t k = 1;
  // When set, only ids it accepts are returned (e.g. a position prior).
  std::function<bool(uint64_t)> accept;
  // The query is a code compared as a unit vector, as AddNormalized's codes
  // are: distances are to core::UnitScale(query) times it, so a code
  // finds a stored copy of itself at distance exactly 0.
  bool unit_query = false;
  // When set, an index that can also copies the code of each neighbour it
  // returns (as CopyCode) into it, in order, in the same turn of its lock
  // (a query waits for that lock once); one that cannot leaves it empty,
  // and the caller reads them with CopyCodes.
  std::vector<std::vector<float>>* codes = nullptr;
};

// Not thread-safe for writers: the caller serialises Add/Remove against each
// other and against Search (Search calls may run concurrently).
class PlaceIndex {
 public:
  virtual ~PlaceIndex() = default;

  // Adds vectors of the index's dimension under new ids. INVALID_ARGUMENT on
  // a wrong dimension or a used id; nothing is added then.
  virtual absl::Status Add(std::span<const uint64_t> ids,
                           std::span<const std::vector<float>> vectors) = 0;
  // Add(ids, the codes scaled to unit length by core::NormalizedCode), with
  // the same checks. The engine indexes its traces' codes this way; an index
  // that can scale while it stores overrides it and saves the copies (a
  // restart at 1,000,000 256-d traces would allocate 1 GB for them).
  virtual absl::Status AddNormalized(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) {
    std::vector<std::vector<float>> vectors;
    vectors.reserve(codes.size());
    for (std::span<const float> code : codes) {
      vectors.push_back(core::NormalizedCode(code));
    }
    return Add(ids, vectors);
  }
  // AddNormalized without the throttling an index may apply while its
  // search structure lags behind (the tiered index's back-pressure): it
  // takes these at once. The caller then either does that work itself with
  // CatchUp, outside its own locks so that its readers go on meanwhile
  // (the engine's uploads), or leaves the index to catch up in the
  // background (a restart's load).
  virtual absl::Status AddNormalizedUnthrottled(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) {
    return AddNormalized(ids, codes);
  }
  // The throttling AddNormalized would have applied to the `added` vectors
  // just given to AddNormalizedUnthrottled (the tiered index: while more
  // than max_unindexed vectors wait for its graph, up to `added` of them
  // move in, a step at a time). Searches may run meanwhile. Default:
  // nothing to do.
  virtual absl::Status CatchUp(size_t added) { return absl::OkStatus(); }
  // True if the index keeps the code or vector it was given under `id` bit
  // for bit (for AddNormalized, the code before scaling), so that the caller
  // may drop its own copy and read it back with CopyCode. Once true it stays
  // true until Remove(id). false by default: the caller keeps its codes.
  // Counts as a reader.
  virtual bool HoldsCode(uint64_t id) const { return false; }
  // HoldsCode of each of `ids` (held[i] for ids[i]), in one turn of the
  // index's lock where it has one.
  virtual std::vector<bool> HoldsCodes(std::span<const uint64_t> ids) const {
    std::vector<bool> held(ids.size());
    for (size_t i = 0; i < ids.size(); ++i) held[i] = HoldsCode(ids[i]);
    return held;
  }
  // Sets *code to what HoldsCode promises; false, changing nothing, when
  // the index does not hold it. Counts as a reader.
  virtual bool CopyCode(uint64_t id, std::vector<float>* code) const {
    return false;
  }
  // CopyCode of each of `ids` into *codes[i], in one turn of the index's
  // lock where it has one (a query's k matches, a cluster's codes); false
  // if any is not held. Counts as a reader.
  virtual bool CopyCodes(std::span<const uint64_t> ids,
                         std::span<std::vector<float>* const> codes) const {
    bool all = true;
    for (size_t i = 0; i < ids.size(); ++i) {
      all = CopyCode(ids[i], codes[i]) && all;
    }
    return all;
  }
  // Removes ids; unknown ids are ignored.
  virtual absl::Status Remove(std::span<const uint64_t> ids) = 0;
  // Up to params.k nearest accepted vectors, nearest first (ties: smaller id).
  virtual absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const = 0;
  virtual size_t size() const = 0;
  virtual size_t dimension() const = 0;
  // Vectors held but not yet in the index's search structure (searched by
  // an exact scan meanwhile), e.g. a graph index's backlog; 0 by default.
  virtual size_t unindexed() const { return 0; }

  // A bulk load (ImportTraces): until `until`, the index may leave the
  // vectors it is given outside its search structure (found by an exact
  // scan meanwhile, as unindexed()) and do none of that work, in the
  // background or as back-pressure; the structure is then built once,
  // from all of them, by IndexWaiting. A time already past ends the
  // deferral (the background work resumes). A writer. Default: nothing to
  // defer.
  virtual void DeferIndexing(absl::Time until) {}
  // Ends any deferral and brings every waiting vector into the search
  // structure now, on the index's insert threads (the caller's among them),
  // in large steps with searches let in between; returns once none waits
  // (or with the error that stopped it: the rest stay searchable by the
  // exact scan). A writer. Default: nothing waits.
  virtual absl::Status IndexWaiting() { return absl::OkStatus(); }

  // Writes everything the index holds (ids, vectors, a graph's links) so
  // that Load into an empty index of the same kind, dimension and build
  // options gives the same answers: a restart that skips rebuilding a
  // graph. Counts as a reader (concurrent Search calls are fine).
  // UNIMPLEMENTED, writing nothing, for an index that cannot.
  virtual absl::Status Save(core::ByteWriter& out) const {
    return absl::UnimplementedError("this index cannot be saved");
  }
  // Called once the bytes of the last Save, made to a file
  // (core::ByteWriter::file), are all in it: an index may then read what
  // it holds outside memory from that file instead of its own copy (an
  // int8 graph's floats, core::HnswGraph::AdoptSavedFloats), unless it
  // changed since. A writer. Default: nothing.
  virtual void SavedToFile() {}
  // Restores what Save wrote into this empty index (a writer); from a
  // file (core::ByteReader::file), an index may keep reading parts of it
  // from there. DATA_LOSS
  // when the bytes are malformed or come from another kind of index or other
  // options (the index is then unusable: discard it); UNIMPLEMENTED for an
  // index that cannot.
  virtual absl::Status Load(core::ByteReader& in) {
    return absl::UnimplementedError("this index cannot be loaded");
  }
  // True once a read of what the index keeps outside memory met damage (a
  // row of an index snapshot's file that failed its own checksum: the call
  // that needed it got DATA_LOSS, never a wrong answer); the engine then
  // rebuilds the index from the store. Thread-safe. Default: false.
  virtual bool Damaged() const { return false; }
};

// Makes an empty index of `dimension` for one fleet.
using PlaceIndexFactory =
    std::function<std::unique_ptr<PlaceIndex>(size_t dimension)>;
// Makes an empty index for a fleet whose settings name its own
// (IndexSettings::kind other than kServer).
using FleetIndexFactory = std::function<std::unique_ptr<PlaceIndex>(
    size_t dimension, const IndexSettings& index)>;

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_PLACE_INDEX_H_
