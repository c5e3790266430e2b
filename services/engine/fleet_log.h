// The log port of the engine: each fleet's log, the writes it acknowledged
// in order, kept until they are applied (engine/log_applier.h) — the one
// log both modes write. Apart from the storage port (memory_store.h), which
// holds the applied state only. Implementations:
//  - services/storage/segment_log.h: segment files beside the RocksDB store
//    (embedded mode; opened with it, OpenLocalStorage);
//  - services/cluster/nats_fleet_log.h: a JetStream stream per fleet,
//    replicated (distributed mode);
//  - services/storage/in_memory_log.h: tests.
// An entry is a record (an upload, or a call whose effect every replica
// must agree on: Consolidate, SampleReplay, DeleteTraces, UpdateRewards,
// CreateFleet, UpdateFleet)
// under a sequence the log
// chooses, growing; a log may skip numbers (JetStream does when a proposal
// fails as its leader changes).
#ifndef FLEETMEM_SERVICES_ENGINE_FLEET_LOG_H_
#define FLEETMEM_SERVICES_ENGINE_FLEET_LOG_H_

#include <cstdint>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <variant>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/core/trace_filter.h"
#include "services/core/types.h"
#include "services/engine/fleet_settings.h"

namespace fleetmem::engine {

// A record to append or apply, its traces and strings not copied.
struct UploadRecord {
  std::span<const core::MemoryTrace> traces;  // one robot's or several
};
struct ConsolidateRecord {};
struct SampleReplayRecord {
  std::string_view robot_id;
  uint64_t count = 0;
  std::string_view request_id;
  // Only matching traces are drawn; null: any.
  const core::ReadFilter* filter = nullptr;
};
// A DeleteTraces call: the traces `filter` matches when it is applied.
struct DeleteTracesRecord {
  core::TraceFilter filter;
};
struct UpdateRewardsRecord {
  std::span<const core::RewardUpdate> updates;
};
// A CreateFleet call: a fleet's first entry (AppendOptions::only_first),
// its shape and settings.
struct CreateFleetRecord {
  uint32_t code_dimension = 0;
  std::string encoder_version;
  FleetSettings settings;
};
// An UpdateFleet call.
struct UpdateFleetRecord {
  FleetSettingsUpdate update;
};
// Retention's deletes (FleetSettings::max_age_seconds,
// max_traces_per_robot) as of `now_ns`, the clock of the server that
// appended it: every replica deletes the same traces.
struct EnforceRetentionRecord {
  int64_t now_ns = 0;
};
// A DeleteFleet call: the fleet's state goes; entries after it make the
// fleet anew (MemoryEngine::DeleteFleet).
struct DeleteFleetRecord {};
using LogRecord =
    std::variant<UploadRecord, ConsolidateRecord, SampleReplayRecord,
                 DeleteTracesRecord, UpdateRewardsRecord, CreateFleetRecord,
                 UpdateFleetRecord, EnforceRetentionRecord, DeleteFleetRecord>;

// A record as read back from a log: it owns what it holds.
struct SampleReplayCall {
  std::string robot_id;
  uint64_t count = 0;
  std::string request_id;
  core::ReadFilter filter;
};
struct UpdateRewardsCall {
  std::vector<core::RewardUpdate> updates;
};
using StoredRecord =
    std::variant<std::vector<core::MemoryTrace>, ConsolidateRecord,
                 SampleReplayCall, DeleteTracesRecord, UpdateRewardsCall,
                 CreateFleetRecord, UpdateFleetRecord, EnforceRetentionRecord,
                 DeleteFleetRecord>;

// One entry of a fleet's log, as read.
struct LogEntry {
  uint64_t sequence = 0;
  // The id it was appended under, where the log keeps ids (JetStream);
  // empty otherwise.
  std::string id;
  StoredRecord record;

  // An upload's traces; empty for a call. (Inline: the ports target is
  // header-only.)
  std::span<const core::MemoryTrace> traces() const {
    const auto* upload = std::get_if<std::vector<core::MemoryTrace>>(&record);
    return upload == nullptr ? std::span<const core::MemoryTrace>()
                             : std::span<const core::MemoryTrace>(*upload);
  }
  // The record as the applier takes it (views into this entry).
  LogRecord view() const {
    if (const auto* call = std::get_if<SampleReplayCall>(&record)) {
      return SampleReplayRecord{
          call->robot_id, call->count, call->request_id,
          call->filter.selects_all() ? nullptr : &call->filter};
    }
    if (std::holds_alternative<ConsolidateRecord>(record)) {
      return ConsolidateRecord{};
    }
    if (const auto* call = std::get_if<DeleteTracesRecord>(&record)) {
      return *call;
    }
    if (const auto* call = std::get_if<UpdateRewardsCall>(&record)) {
      return UpdateRewardsRecord{call->updates};
    }
    if (const auto* call = std::get_if<CreateFleetRecord>(&record)) {
      return *call;
    }
    if (const auto* call = std::get_if<UpdateFleetRecord>(&record)) {
      return *call;
    }
    if (const auto* call = std::get_if<EnforceRetentionRecord>(&record)) {
      return *call;
    }
    if (std::holds_alternative<DeleteFleetRecord>(record)) {
      return DeleteFleetRecord{};
    }
    return UploadRecord{traces()};
  }
};

// An entry to append.
struct LogAppend {
  LogRecord record;
  // A log that deduplicates (JetStream) stores one entry per id within its
  // window: a retry of an append whose answer was lost is not stored
  // twice. Empty: none. A local log ignores it (its writer admits each
  // (robot, seq) once, engine/admission.h).
  std::string_view id;
};

// One log entry's worth of an upload's traces, and the id it is appended
// under (a replicated log's write path cuts uploads into these).
struct LogPiece {
  std::vector<core::MemoryTrace> traces;
  std::string id;
};

struct AppendOptions {
  // Only as the log's first entries (a fleet's creation):
  // FAILED_PRECONDITION, with nothing appended, if the log ever held an
  // entry. (A log that deduplicates answers a repeat of the first entry's
  // id as a duplicate, as it would without the option: a retry of the
  // upload that created the fleet.)
  bool only_first = false;
  // The entries' sequences are above this too: the writer's own record of
  // its last (after a restart, a writer whose applied state is ahead of a
  // log that lost its tail does not reuse a sequence it applied). A log
  // that cannot choose (JetStream numbers its own) refuses a non-zero one
  // with INVALID_ARGUMENT.
  uint64_t above = 0;
};

// What one appended entry became.
struct AppendedEntry {
  uint64_t sequence = 0;
  // The log held an entry under the same id (within its deduplication
  // window): nothing was added; `sequence` is the earlier entry's.
  bool duplicate = false;
};

// The entries a fleet's log holds: `first` through `last` (a log may have
// skipped numbers between). {0, 0}: none ever; {last + 1, last}: every
// entry trimmed.
struct LogBounds {
  uint64_t first = 0;
  uint64_t last = 0;
};

// Acknowledged log entries that a log found damaged (they fail their
// checksum or frame) and passed over: lost, never applied. The entries
// after them are applied.
struct LostLogEntries {
  uint64_t first = 0;  // sequences, inclusive
  uint64_t last = 0;
  std::string detail;  // where and how, for the log and GetStats
};

// Thread-safe, except that appends of one fleet must not overlap in a
// local log (the write path's group-commit leader makes them one at a
// time); reads and trims may run beside them. Fleet ids are checked by the
// caller (core::ValidateId at the edge). Errors are statuses, never
// throws.
class FleetLog {
 public:
  virtual ~FleetLog() = default;

  // Appends `entries`, in order, and returns once they are durable (synced
  // to disk, or stored on the log's replicas), with the sequence each got.
  // A local log writes them in one atomic write: on error nothing of them
  // is read back, now or after a restart, unless the status says it could
  // not be undone. A replicated log stores them one at a time: on error
  // the status says how many of them it holds (a retry under the same ids
  // stores only the rest).
  virtual absl::StatusOr<std::vector<AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const LogAppend> entries,
      const AppendOptions& options) = 0;

  // Up to `max_entries` entries of the fleet's log with sequence > `after`,
  // ascending (none for a fleet without a log). Damaged entries are passed
  // over (Losses). OUT_OF_RANGE where the log can tell that entries after
  // `after` were trimmed (JetStream; a snapshot holds them).
  virtual absl::StatusOr<std::vector<LogEntry>> Read(std::string_view fleet_id,
                                                     uint64_t after,
                                                     size_t max_entries) = 0;

  // Erases the fleet's entries with sequence <= `through`, once what they
  // carry is applied (embedded mode) or in a snapshot (distributed mode).
  // The erasure need not be durable (entries are applied again,
  // idempotently, if it is lost), but an entry must not be erased durably
  // before what it was applied to is: an implementation beside a store
  // whose applies of log entries are unsynced (FleetMutation::sync) makes
  // them durable first. A log may keep entries at or below `through` (Read
  // of later entries passes over them). Sequences are never reused.
  virtual absl::Status Trim(std::string_view fleet_id, uint64_t through) = 0;

  // The fleet's bounds ({0, 0} for a fleet without a log).
  virtual absl::StatusOr<LogBounds> Bounds(std::string_view fleet_id) = 0;

  // The fleets that have a log, sorted.
  virtual absl::StatusOr<std::vector<std::string>> Fleets() = 0;

  // The fleet's entries found damaged since the log opened (at open, or
  // when Read met them), in the order found. Empty for a log that cannot
  // be damaged (in memory, or replicated).
  virtual std::vector<LostLogEntries> Losses(std::string_view fleet_id) {
    return {};
  }
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_FLEET_LOG_H_
