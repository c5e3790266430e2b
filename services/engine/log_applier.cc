#include "services/engine/log_applier.h"

#include <string>
#include <utility>

#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"

namespace fleetmem::engine {
namespace {

// Applies one kind of record: the engine's answer, with what it did.
struct Apply {
  MemoryEngine& engine;
  std::string_view fleet_id;
  uint64_t sequence;
  AppliedRecord& applied;

  absl::Status operator()(const UploadRecord& upload) const {
    absl::StatusOr<UploadResult> result =
        engine.Upload(fleet_id, upload.traces, sequence);
    if (!result.ok()) return result.status();
    applied.consolidations = result->consolidations;
    applied.duplicates = result->duplicates;
    return absl::OkStatus();
  }
  absl::Status operator()(const ConsolidateRecord&) const {
    absl::StatusOr<ConsolidateResult> result = engine.Consolidate(fleet_id);
    if (!result.ok()) return result.status();
    applied.consolidated = *result;
    return absl::OkStatus();
  }
  absl::Status operator()(const SampleReplayRecord& call) const {
    absl::StatusOr<std::vector<core::MemoryTrace>> sample =
        engine.SampleReplay(fleet_id, call.robot_id, call.count,
                            call.request_id, sequence, call.filter);
    if (!sample.ok()) return sample.status();
    applied.sample = *std::move(sample);
    return absl::OkStatus();
  }
  absl::Status operator()(const DeleteTracesRecord& call) const {
    absl::StatusOr<DeleteResult> result =
        engine.DeleteTraces(fleet_id, call.filter, sequence);
    if (!result.ok()) return result.status();
    applied.deleted = *result;
    return absl::OkStatus();
  }
  absl::Status operator()(const CreateFleetRecord& call) const {
    return engine.CreateFleet(fleet_id, call, sequence);
  }
  absl::Status operator()(const UpdateFleetRecord& call) const {
    absl::StatusOr<FleetSettings> result =
        engine.UpdateFleet(fleet_id, call.update, sequence);
    if (!result.ok()) return result.status();
    applied.settings = *std::move(result);
    return absl::OkStatus();
  }
  absl::Status operator()(const EnforceRetentionRecord& call) const {
    absl::StatusOr<DeleteResult> result =
        engine.EnforceRetention(fleet_id, call.now_ns, sequence);
    if (!result.ok()) return result.status();
    applied.deleted = *result;
    return absl::OkStatus();
  }
  absl::Status operator()(const DeleteFleetRecord&) const {
    absl::StatusOr<uint64_t> traces = engine.DeleteFleet(fleet_id, sequence);
    if (!traces.ok()) return traces.status();
    applied.fleet_deleted = *traces;
    return absl::OkStatus();
  }
  absl::Status operator()(const UpdateRewardsRecord& call) const {
    absl::StatusOr<RewardsResult> result =
        engine.UpdateRewards(fleet_id, call.updates, sequence);
    if (!result.ok()) return result.status();
    applied.rescored = *std::move(result);
    return absl::OkStatus();
  }
};

}  // namespace

bool RefusedByState(const absl::Status& status) {
  return absl::IsInvalidArgument(status) ||
         absl::IsFailedPrecondition(status) || absl::IsNotFound(status);
}

absl::StatusOr<AppliedRecord> ApplyLogRecord(MemoryEngine& engine,
                                             std::string_view fleet_id,
                                             uint64_t sequence,
                                             const LogRecord& record) {
  AppliedRecord applied;
  const absl::Status status =
      std::visit(Apply{engine, fleet_id, sequence, applied}, record);
  if (status.ok()) return applied;
  if (!RefusedByState(status)) return status;
  // Every replica refuses it alike; the log moves on. An upload was
  // admitted as the engine checks it: only a change of the checks between
  // two versions makes the engine refuse one now.
  const bool upload = std::holds_alternative<UploadRecord>(record);
  log::Write(
      upload ? log::Level::kError : log::Level::kWarning, __FILE__, __LINE__,
      absl::StrCat(
          "fleet \"", V(fleet_id), "\": log entry ", sequence,
          upload ? absl::StrCat(" (an acknowledged upload of ",
                                std::get<UploadRecord>(record).traces.size(),
                                " traces)")
                 : std::string(),
          " refused when applied, passed over: ", status.ToString()));
  applied.refused = status;
  return applied;
}

absl::StatusOr<AppliedTurn> LogApplier::Turn(std::string_view fleet_id,
                                             uint64_t position,
                                             size_t max_entries,
                                             const ApplyHooks& hooks) {
  absl::StatusOr<std::vector<LogEntry>> entries =
      log_->Read(fleet_id, position, max_entries);
  if (!entries.ok()) return entries.status();
  AppliedTurn turn;
  turn.position = position;
  for (const LogEntry& entry : *entries) {
    if (hooks.may_apply && !hooks.may_apply(entry)) break;
    absl::StatusOr<AppliedRecord> applied =
        ApplyLogRecord(*engine_, fleet_id, entry.sequence, entry.view());
    if (!applied.ok()) {
      // The store (a full disk): applied again later, never passed.
      turn.stopped = applied.status();
      break;
    }
    turn.position = entry.sequence;
    ++turn.applied;
    if (hooks.applied) hooks.applied(entry, *applied);
  }
  return turn;
}

}  // namespace fleetmem::engine
