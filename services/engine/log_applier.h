// The deterministic apply of one entry of a fleet's log, the one both modes
// run: embedded mode's appliers (write_path.h) over the local ingest log,
// and distributed mode's owner (cluster/materialiser.h) over JetStream.
// Every replica that applies the same entries in the same order reaches the
// same memory: uploads are stored with the entry's sequence
// (MemoryEngine::LogPosition), so an entry applied again changes nothing;
// consolidation is seeded per segment; a sample is drawn under the entry's
// sequence.
//
// What happens to an entry the memory refuses is decided here, once:
//  - refused by the fleet's state (INVALID_ARGUMENT, FAILED_PRECONDITION,
//    NOT_FOUND): every replica refuses it alike, so it is passed (logged);
//    the answer carries the refusal (AppliedRecord::refused);
//  - any other error: returned, nothing is passed; the caller applies the
//    entry again later. RESOURCE_EXHAUSTED is among these: a full disk (the
//    store's reserve) says it too, and passing the entry then would lose it
//    on this replica.
#ifndef FLEETMEM_SERVICES_ENGINE_LOG_APPLIER_H_
#define FLEETMEM_SERVICES_ENGINE_LOG_APPLIER_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <span>
#include <string_view>
#include <variant>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/core/types.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_engine.h"

namespace fleetmem::engine {

// What applying an entry did.
struct AppliedRecord {
  // OK, or the fleet's state's refusal (the entry was passed).
  absl::Status refused;
  uint64_t consolidations = 0;  // an upload's (segments it filled)
  // An upload's traces the fleet had received already (by an earlier entry:
  // embedded mode admits none such, distributed mode may log a retry twice).
  uint64_t duplicates = 0;
  ConsolidateResult consolidated;         // a ConsolidateRecord's
  std::vector<core::MemoryTrace> sample;  // a SampleReplayRecord's
  DeleteResult deleted;                   // a DeleteTracesRecord's
  uint64_t fleet_deleted = 0;             // a DeleteFleetRecord's traces
  RewardsResult rescored;                 // an UpdateRewardsRecord's
  FleetSettings settings;                 // an UpdateFleetRecord's, after
};

// True for the statuses every replica answers alike from the fleet's state
// (the entry is passed), false for the store's errors (retried).
bool RefusedByState(const absl::Status& status);

// Applies `record`, the fleet's log entry at `sequence`, to `engine` (which
// must run without upload rates: a refusal by the clock would make replicas
// differ). The store's error, or what it did.
absl::StatusOr<AppliedRecord> ApplyLogRecord(MemoryEngine& engine,
                                             std::string_view fleet_id,
                                             uint64_t sequence,
                                             const LogRecord& record);

// What LogApplier::Turn did.
struct AppliedTurn {
  // The last entry applied (or passed, refused by the state): the
  // caller's position from now on.
  uint64_t position = 0;
  size_t applied = 0;  // entries applied (or passed) in the turn
  // The store's error that stopped the turn at the entry after `position`
  // (it stays unapplied: apply it again later); OK otherwise.
  absl::Status stopped;
};

// What the caller of a turn hears and decides, entry by entry.
struct ApplyHooks {
  // Asked before each entry: false ends the turn before it (an owner's
  // lease is due for renewal; a stop; an entry past what the caller
  // knows acknowledged). Empty: every entry read is applied.
  std::function<bool(const LogEntry& entry)> may_apply;
  // Told of each entry applied or passed, with what it did.
  std::function<void(const LogEntry& entry, const AppliedRecord& applied)>
      applied;
};

// The one applier of both modes: a fleet's log, read from a position and
// applied in order to the engine. Embedded mode's write path
// (write_path.h) runs turns on its applier threads, over the local log,
// and trims what they applied; distributed mode's owner
// (cluster/materialiser.h) runs them under its lease, over JetStream, and
// trims below its snapshots. Thread-safe; turns of one fleet must not
// overlap (each caller runs a fleet's turns one at a time).
class LogApplier {
 public:
  // `log` and `engine` must outlive it.
  LogApplier(FleetLog* log, MemoryEngine* engine)
      : log_(log), engine_(engine) {}

  // Reads up to `max_entries` entries after `position` and applies them in
  // order (ApplyLogRecord), until a hook ends the turn or the store fails
  // (AppliedTurn::stopped). The log's read error as it says it
  // (OUT_OF_RANGE: trimmed past `position`; a snapshot holds the entries).
  absl::StatusOr<AppliedTurn> Turn(std::string_view fleet_id, uint64_t position,
                                   size_t max_entries,
                                   const ApplyHooks& hooks = {});

  FleetLog& log() const { return *log_; }

 private:
  FleetLog* const log_;
  MemoryEngine* const engine_;
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_LOG_APPLIER_H_
