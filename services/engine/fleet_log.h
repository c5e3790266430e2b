// The log port of the engine: each fleet's ingest log, the uploads it
// acknowledged in order, kept until they are applied (engine/write_path.h).
// Apart from the storage port (memory_store.h), which holds the applied
// state only. Implementations: services/storage/segment_log.h (segment
// files beside the RocksDB store, opened with it: OpenLocalStorage), and
// services/storage/in_memory_log.h (tests).
#ifndef FLEETMEM_SERVICES_ENGINE_FLEET_LOG_H_
#define FLEETMEM_SERVICES_ENGINE_FLEET_LOG_H_

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/core/types.h"

namespace fleetmem::engine {

// One entry of a fleet's log: an upload as it was acknowledged, under its
// sequence in the fleet's log.
struct LoggedUpload {
  uint64_t sequence = 0;
  std::vector<core::MemoryTrace> traces;
};

// Acknowledged log entries that a log found damaged (they fail their
// checksum or frame) and passed over: lost, never applied. The entries
// after them are applied.
struct LostLogEntries {
  uint64_t first = 0;  // sequences, inclusive
  uint64_t last = 0;
  std::string detail;  // where and how, for the log and GetStats
};

// An entry to append (FleetLog::Append), its traces not copied.
struct LogAppend {
  uint64_t sequence = 0;
  std::span<const core::MemoryTrace> traces;
};

// Thread-safe, except that appends of one fleet must not overlap (the
// write path's group-commit leader makes them one at a time); reads and
// trims may run beside them. Fleet ids are checked by the caller
// (core::ValidateId at the edge). Errors are statuses, never throws.
class FleetLog {
 public:
  virtual ~FleetLog() = default;

  // Appends `entries` (each sequence greater than every one the fleet's log
  // held) in one atomic write and returns once they are durable (synced).
  // On error nothing of them is read back, now or after a restart, unless
  // the status says it could not be undone.
  virtual absl::Status Append(std::string_view fleet_id,
                              std::span<const LogAppend> entries) = 0;

  // Up to `max_entries` entries of the fleet's log with sequence > `after`,
  // ascending (none for a fleet without a log). Damaged entries are passed
  // over (Losses).
  virtual absl::StatusOr<std::vector<LoggedUpload>> Read(
      std::string_view fleet_id, uint64_t after, size_t max_entries) = 0;

  // Erases the fleet's entries with sequence <= `through`, once what they
  // carry is applied. The erasure need not be durable (entries are applied
  // again, idempotently, if it is lost), but an entry must not be erased
  // durably before what it was applied to is: an implementation beside a
  // store whose applies of log entries are unsynced (FleetMutation::sync)
  // makes them durable first. A log may keep entries at or below `through`
  // (Read of later entries passes over them).
  virtual absl::Status Trim(std::string_view fleet_id, uint64_t through) = 0;

  // The fleets whose log holds entries, each with its last sequence;
  // sorted by fleet.
  virtual absl::StatusOr<std::vector<std::pair<std::string, uint64_t>>>
  Tails() = 0;

  // The fleet's entries found damaged since the log opened (at open, or
  // when Read met them), in the order found. Empty for a log that cannot
  // be damaged (in memory).
  virtual std::vector<LostLogEntries> Losses(std::string_view fleet_id) {
    return {};
  }
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_FLEET_LOG_H_
