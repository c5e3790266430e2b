#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <random>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#include "services/engine/memory_engine.h"

#if __has_include(<malloc.h>)
#include <malloc.h>
#endif

#include "absl/cleanup/cleanup.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/feature_space.h"
#include "services/core/static_memory.h"
#include "services/core/validation.h"
#include "services/engine/memory_engine_fleet.h"
#include "services/engine/trace_handles.h"

namespace fleetmem::engine {

size_t MemoryEngine::ReleaseIndexedCodes() {
  std::vector<Fleet*> fleets;
  {
    absl::ReaderMutexLock lock(&fleets_mu_);
    for (const auto& [fleet_id, fleet] : fleets_) fleets.push_back(fleet.get());
  }
  size_t released = 0;
  for (Fleet* fleet : fleets) {
    absl::MutexLock lock(&fleet->mu);
    released += fleet->ReleaseAllCodes();
  }
  // Large releases leave holes amid the heap that glibc keeps.
  if (released >= 10'000) ReturnFreedMemory();
  return released;
}

absl::Status MemoryEngine::SaveIndexSnapshots(
    const IndexSnapshotSelection& which) {
  std::vector<Fleet*> fleets;
  {
    absl::ReaderMutexLock lock(&fleets_mu_);
    for (const auto& [fleet_id, fleet] : fleets_) fleets.push_back(fleet.get());
  }
  absl::Status first;
  for (Fleet* fleet : fleets) {
    // One snapshot of a fleet at a time (they share the store's file).
    absl::MutexLock one_at_a_time(&fleet->snapshot_mu);
    // An index that met damage in its snapshot's file (a row that failed
    // its check) is rebuilt from the store first: this save replaces the
    // file with one written from the store's codes. (Asked under the shared
    // lock: queries go on.)
    if (fleet->IndexDamaged()) {
      absl::MutexLock writer(&fleet->writer_mu);
      absl::MutexLock lock(&fleet->mu);
      if (absl::Status rebuilt = fleet->EnsureLoaded(); !rebuilt.ok()) {
        first.Update(rebuilt);
        continue;
      }
    }
    // writer_mu keeps every change out while the snapshot is written;
    // queries go on beside the shared lock (no writer waits for `mu`
    // without holding writer_mu first). Both are released once the store
    // holds the bytes, before it syncs them.
    fleet->writer_mu.Lock();
    fleet->mu.ReaderLock();
    bool locked = true;
    absl::Time released;
    auto release = [&]() ABSL_NO_THREAD_SAFETY_ANALYSIS {
      if (!locked) return;
      locked = false;
      fleet->mu.ReaderUnlock();
      fleet->writer_mu.Unlock();
      released = absl::Now();
    };
    absl::Cleanup release_on_exit = [&] { release(); };  // every way out
    // A fleet without traces loads fast and would never take its file.
    const FleetIndex& index = fleet->index;
    if (!fleet->stale.ok() || !fleet->exists() || index.get() == nullptr ||
        index.size() == 0 || index.size() < which.min_codes ||
        (which.only_changed && index.SnapshotCurrent() &&
         (!which.refresh_memory_image ||
          store_->IndexSnapshotCurrent(fleet->id)))) {
      continue;
    }
    const uint64_t changes = index.changes();
    const size_t codes = index.size();
    const size_t unindexed = index.get()->unindexed();
    const absl::Time start = absl::Now();
    absl::Status status = fleet->SaveIndexSnapshot(release);
    release();  // the store did not call it (an error, or nothing to sync)
    if (absl::IsUnimplemented(status)) continue;  // this kind of index
    if (!status.ok()) {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << fleet->id << "\": no index snapshot: " << status;
      first.Update(status);
      continue;
    }
    {
      absl::MutexLock writer(&fleet->writer_mu);
      absl::MutexLock lock(&fleet->mu);
      fleet->index.SnapshotWritten(changes, unindexed);
    }
    const double held = absl::ToDoubleSeconds(released - start);
    FLEETMEM_LOG(kInfo) << "fleet \"" << fleet->id << "\": index snapshot of "
                        << codes << " codes saved in "
                        << absl::ToDoubleSeconds(absl::Now() - start)
                        << " s (uploads waited " << held << " s)";
    if (hooks_.on_index_snapshot) hooks_.on_index_snapshot(fleet->id, held);
  }
  return first;
}

absl::StatusOr<FleetImage> MemoryEngine::ExportFleet(std::string_view fleet_id,
                                                     uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  absl::MutexLock writer(&fleet->writer_mu);
  {
    absl::MutexLock lock(&fleet->mu);
    status = fleet->EnsureLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) {
      // Deleted (DeleteFleet kept its position and ids): an image of no
      // traces that restores the deletion on another replica.
      if (fleet->meta.log_position == 0) return FleetNotFound(fleet_id);
      FleetImage deleted;
      deleted.record.fleet_id = fleet->id;
      deleted.record.meta = fleet->meta;
      deleted.record.meta.log_position =
          std::max(log_position, fleet->meta.log_position);
      return deleted;
    }
    if (log_position > fleet->meta.log_position) {
      FleetMutation mutation;
      mutation.put_meta = true;
      mutation.meta = fleet->meta;
      mutation.meta.log_position = log_position;
      status = store_->Apply(fleet->id, mutation);
      if (!status.ok()) return status;
      fleet->meta.log_position = log_position;
    }
  }
  // The writer lock keeps every change out; readers go on.
  FleetImage image;
  absl::StatusOr<FleetRecord> record = store_->LoadFleet(fleet_id);
  if (!record.ok()) return record.status();
  image.record = *std::move(record);
  constexpr size_t kEventsPerRead = 10000;
  uint64_t after = 0;
  while (true) {
    absl::StatusOr<std::vector<core::MemoryEvent>> events =
        store_->ReadEvents(fleet_id, after, kEventsPerRead);
    if (!events.ok()) return events.status();
    if (events->empty()) break;
    after = events->back().id;
    const bool last = events->size() < kEventsPerRead;
    image.events.insert(image.events.end(),
                        std::make_move_iterator(events->begin()),
                        std::make_move_iterator(events->end()));
    if (last) break;
  }
  return image;
}

absl::Status MemoryEngine::RestoreFleet(std::string_view fleet_id,
                                        FleetImage image) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  if (image.record.fleet_id != fleet_id) {
    return absl::InvalidArgumentError(
        absl::StrCat("an image of fleet \"", image.record.fleet_id,
                     "\" cannot restore fleet \"", V(fleet_id), "\""));
  }
  const bool deleted = image.record.meta.code_dimension == 0;
  if (deleted &&
      (image.record.meta.log_position == 0 || !image.record.pending.empty() ||
       !image.record.clusters.empty())) {
    return absl::InvalidArgumentError(
        absl::StrCat("the image of fleet \"", V(fleet_id),
                     "\" holds no upload (no code dimension) and is not a "
                     "deleted fleet's"));
  }
  absl::StatusOr<Fleet*> found = Fleet::FindOrAdd(*this, fleet_id);
  if (!found.ok()) return found.status();
  Fleet* fleet = *found;
  if (deleted) return RestoreDeletedFleet(*fleet, image.record.meta);
  uint64_t last_event_id = 0;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    // What the store holds is erased, whatever memory holds.
    absl::StatusOr<FleetRecord> stored = store_->LoadFleet(fleet_id);
    if (!stored.ok()) return stored.status();
    FleetMutation mutation;
    for (const core::MemoryTrace& trace : stored->pending) {
      mutation.erase_pending.push_back(trace.key());
    }
    for (const core::Cluster& cluster : stored->clusters) {
      mutation.erase_clusters.push_back(cluster.id);
    }
    // Events are put over the stored ones of the same ids (a replica's
    // state is a prefix of the image's). Erasure applies after the puts:
    // only the events the image's retention dropped.
    if (image.record.meta.first_event_id > 1) {
      mutation.erase_events_before = image.record.meta.first_event_id;
    }
    mutation.put_meta = true;
    mutation.meta = image.record.meta;
    mutation.put_pending = std::move(image.record.pending);
    mutation.put_clusters = std::move(image.record.clusters);
    mutation.put_robots = std::move(image.record.robots);
    mutation.append_events = std::move(image.events);
    last_event_id = mutation.meta.next_event_id - 1;
    absl::MutexLock lock(&fleet->mu);
    status = store_->Apply(fleet->id, mutation);
    if (!status.ok()) return status;
    status = fleet->Reload();
  }
  if (status.ok()) Fleet::Notify(*this, fleet_id, last_event_id);
  return status;
}

absl::Status MemoryEngine::RestoreDeletedFleet(Fleet& fleet,
                                               const FleetMeta& kept) {
  // As DeleteFleet: no index snapshot written behind it.
  absl::MutexLock snapshots(&fleet.snapshot_mu);
  absl::MutexLock writer(&fleet.writer_mu);
  absl::Status status = store_->DeleteFleet(fleet.id, kept);
  if (!status.ok()) return status;  // one write: nothing was changed
  absl::MutexLock lock(&fleet.mu);
  status = fleet.Reload();
  if (!status.ok()) return status;
  FLEETMEM_LOG(kInfo) << "fleet \"" << fleet.id
                      << "\" restored as deleted at log entry "
                      << kept.log_position;
  return absl::OkStatus();
}

absl::Status MemoryEngine::Checkpoint(const std::string& directory) {
  return store_->Checkpoint(directory);
}

}  // namespace fleetmem::engine
