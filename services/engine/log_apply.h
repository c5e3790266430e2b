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
#ifndef FLEETMEM_SERVICES_ENGINE_LOG_APPLY_H_
#define FLEETMEM_SERVICES_ENGINE_LOG_APPLY_H_

#include <cstdint>
#include <span>
#include <string_view>
#include <variant>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/core/types.h"
#include "services/engine/memory_engine.h"

namespace fleetmem::engine {

// The kinds of entry a fleet's log holds (the traces and strings are not
// copied: they live in the entry read from the log).
struct UploadRecord {
  std::span<const core::MemoryTrace> traces;
};
struct ConsolidateRecord {};
struct SampleReplayRecord {
  std::string_view robot_id;
  uint64_t count = 0;
  std::string_view request_id;
};
using LogRecord =
    std::variant<UploadRecord, ConsolidateRecord, SampleReplayRecord>;

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

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_LOG_APPLY_H_
