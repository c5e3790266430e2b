// One fleet's place index under trace keys: the read side of
// MemoryEngine::Fleet (memory_engine_fleet.h). A PlaceIndex over handles,
// the table of which trace each handle is (TraceHandles), the next handle
// to give, and what the fleet's index snapshot must know of them: how many
// changes were made since the fleet was loaded, and at which of them the
// snapshot on disk was written.
//
// Not thread-safe: the fleet's lock guards it (searches and code copies
// under its shared lock, changes under its exclusive lock).
#ifndef FLEETMEM_SERVICES_ENGINE_FLEET_INDEX_H_
#define FLEETMEM_SERVICES_ENGINE_FLEET_INDEX_H_

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "services/core/byte_stream.h"
#include "services/core/types.h"
#include "services/engine/place_index.h"
#include "services/engine/trace_handles.h"

namespace fleetmem::engine {

class FleetIndex {
 public:
  // Whether a load should keep the store's code of the trace under
  // `handle` in a snapshot of `saved` handles, for Reconcile's check: about
  // 1,024 of them, in 32 runs of 32 consecutive handles spread over the
  // handles (every one below 1,056).
  static bool CheckedOnLoad(uint64_t handle, size_t saved);

  // What Reconcile did to a snapshot's index.
  struct Reconciled {
    size_t kept = 0;     // codes of stored traces the snapshot held
    size_t added = 0;    // stored since the snapshot
    size_t removed = 0;  // forgotten or downsampled since the snapshot
  };

  // The index; null before Start (a fleet whose dimension is not known yet)
  // and after Reset.
  PlaceIndex* get() const { return index_.get(); }
  // Codes indexed.
  size_t size() const { return handles_.size(); }

  // No index and no handles; changes count from zero and no snapshot on
  // disk is known to hold this state.
  void Reset();
  // `index` (empty, the engine's factory's for the fleet's dimension) in
  // place of any before, with no handles (and the deferral below).
  void Start(std::unique_ptr<PlaceIndex> index);
  // PlaceIndex::DeferIndexing of this index and of any Start gives it
  // later (a bulk load that makes the fleet, or a reload).
  void DeferIndexing(absl::Time until);
  // The deferral in force (InfinitePast: none).
  absl::Time deferred_until() const { return deferred_until_; }

  // Adds `traces`' (normalised) codes under new handles. `meanwhile`, if
  // given, runs on this thread while another fills the index when there
  // are enough traces for that to pay (a restart); the traces' codes must
  // not change or move meanwhile. Never held up by the index's
  // back-pressure (PlaceIndex::AddNormalizedUnthrottled). INTERNAL without
  // an index.
  absl::Status Add(const std::vector<const core::MemoryTrace*>& traces,
                   const std::function<void()>& meanwhile = nullptr);
  // Removes the codes of those of `keys` it holds.
  absl::Status Remove(const std::vector<core::TraceKey>& keys);

  // The trace under `handle` (a search's neighbour id); nullopt if none.
  std::optional<core::TraceKey> KeyOf(uint64_t handle) const {
    return handles_.Key(handle);
  }
  // The code of `key` copied into *code; false if the index holds none.
  bool CopyCode(const core::TraceKey& key, std::vector<float>* code) const;
  // CopyCode of each key into the code beside it, in one turn of the
  // index's lock; false if any is missing (some may be copied then).
  bool CopyCodes(std::span<const core::TraceKey* const> keys,
                 std::span<std::vector<float>* const> codes) const;
  // For each key: true if the index keeps its code itself
  // (PlaceIndex::HoldsCodes), so that memory may drop its copy.
  std::vector<bool> HoldsCodes(
      std::span<const core::TraceKey* const> keys) const;

  // The index snapshot's parts: the next handle and the handles, then
  // (after what the caller writes between) the index itself.
  void SaveHandles(core::ByteWriter& out) const;
  // The bytes SaveHandles writes.
  uint64_t SavedHandlesSize() const { return 8 + handles_.SavedSize(); }
  absl::Status SaveIndex(core::ByteWriter& out) const;
  // Takes a snapshot's `loaded` index (its `saved` handles, `next_handle`)
  // in place of this one, reconciled with `stored`, the store's traces: a
  // sample of the kept codes must equal the store's (DATA_LOSS naming the
  // first that does not: a snapshot of another history), what the store
  // no longer holds is removed and what the snapshot lacks is added. On an
  // error this index is left empty (Reset): the caller rebuilds it.
  // A stored trace the snapshot holds may come without its code (a load
  // that left it in the store: MemoryStore::LoadFleetWithoutHeldCodes);
  // the sample is of those that have one, and a load keeps the codes of
  // the handles CheckedOnLoad picks for it. A trace without its code is
  // taken to be one of `saved` (the load found it there) and is not looked
  // up; more of them than `saved` holds is DATA_LOSS.
  absl::StatusOr<Reconciled> Reconcile(
      std::unique_ptr<PlaceIndex> loaded, TraceHandles saved,
      uint64_t next_handle,
      const std::vector<const core::MemoryTrace*>& stored);

  // Adds and removes since Reset (failed ones included: they may have
  // changed the index).
  uint64_t changes() const { return changes_; }
  // Something else the snapshot holds changed (forgetting's centroids).
  void MarkChanged() { ++changes_; }
  // The snapshot on disk holds the state after changes() changes, with no
  // fewer codes outside the graph than now (codes the background thread
  // linked since a snapshot holding them unlinked make it stale: a load of
  // it would link them again).
  bool SnapshotCurrent() const {
    return snapshot_at_ == changes_ &&
           (index_ == nullptr || index_->unindexed() >= snapshot_unindexed_);
  }
  // A snapshot of the state after `changes` changes, with `unindexed`
  // codes outside the graph (read before it was taken), is on disk, durably:
  // the index may read from it what it keeps outside memory
  // (PlaceIndex::SavedToFile). A writer.
  void SnapshotWritten(uint64_t changes, size_t unindexed) {
    snapshot_at_ = changes;
    snapshot_unindexed_ = unindexed;
    if (index_ != nullptr) index_->SavedToFile();
  }

 private:
  std::unique_ptr<PlaceIndex> index_;
  TraceHandles handles_;
  uint64_t next_handle_ = 1;
  uint64_t changes_ = 0;
  std::optional<uint64_t> snapshot_at_;
  size_t snapshot_unindexed_ = 0;
  absl::Time deferred_until_ = absl::InfinitePast();
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_FLEET_INDEX_H_
