#include "clients/robot/runtime/migration.h"

#include <algorithm>
#include <chrono>
#include <map>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/runtime/agent.h"
#include "services/core/validation.h"

namespace fleetmem::robot {
namespace {

void Say(const MigrationOptions& options, const std::string& line) {
  if (options.log) options.log(line);
}

absl::Status Stopped(const absl::Status& status, std::string_view step,
                     const MigrationSummary& done) {
  return absl::Status(
      status.code(),
      absl::StrFormat("encoder migration stopped %s: %s (done so far: %d "
                      "re-encoded and acknowledged; rerun to resume)",
                      step, status.message(), done.migrated));
}

// Until the old fleet applied its log through `sequence` (an upload
// acknowledged durable only, as distributed mode answers): GetTraces reads
// what is applied.
absl::Status WaitApplied(const MigrationOptions& options,
                         client::Client& client, uint64_t sequence) {
  const auto give_up = std::chrono::steady_clock::now() + options.apply_wait;
  while (true) {
    absl::StatusOr<v1::GetStatsResponse> stats =
        client.GetStats(options.from_fleet);
    if (!stats.ok()) return stats.status();
    if (stats->applied_through() >= sequence) return absl::OkStatus();
    if (std::chrono::steady_clock::now() >= give_up) {
      return absl::UnavailableError(absl::StrCat(
          "fleet ", options.from_fleet, " applied its log through ",
          stats->applied_through(), ", not yet through ", sequence,
          ", the robot's last upload"));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
}

// Step 1: the queue's traces to the old fleet, applied there.
absl::Status SendQueue(const MigrationOptions& options, client::Client& client,
                       RobotStore& store, MigrationSummary& summary) {
  uint64_t unapplied = 0;
  while (true) {
    absl::StatusOr<std::vector<v1::MemoryTrace>> batch =
        store.PeekQueue(options.batch);
    if (!batch.ok()) return batch.status();
    if (batch->empty()) {
      return unapplied == 0 ? absl::OkStatus()
                            : WaitApplied(options, client, unapplied);
    }
    absl::StatusOr<v1::UploadTracesResponse> sent =
        client.Upload(options.from_fleet, *batch);
    if (!sent.ok()) return sent.status();
    if (!sent->applied()) {
      unapplied = std::max(unapplied, sent->last_sequence());
    }
    absl::Status marked = store.MarkUploaded(
        batch->back().seq(), sent->accepted(), sent->duplicates());
    if (!marked.ok()) return marked;
    summary.queued_sent += batch->size();
  }
}

// A trace of the old fleet re-encoded from its observation.
absl::StatusOr<v1::MemoryTrace> Reencode(const MigrationOptions& options,
                                         const ObservationSource& source,
                                         const Encoder& encoder,
                                         v1::MemoryTrace trace,
                                         uint64_t index) {
  if (index >= source.size()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "seq ", trace.seq(), " was observed at index ", index, " of ",
        source.description(), ", which holds ", source.size()));
  }
  absl::StatusOr<Observation> observation = source.Read(index);
  if (!observation.ok()) return observation.status();
  absl::StatusOr<std::vector<float>> code = encoder.Encode(*observation);
  if (!code.ok()) return code.status();
  if (absl::Status valid = core::ValidateCode(
          absl::StrCat("code of ", observation->name), *code);
      !valid.ok()) {
    return valid;
  }
  absl::StatusOr<float> internal =
      InternalRewardOf(encoder, *observation, *code, options.seed, index);
  if (!internal.ok()) return internal.status();
  trace.mutable_code()->Assign(code->begin(), code->end());
  trace.set_encoder_version(encoder.version());
  trace.set_reward_internal(*internal);
  trace.set_reward(trace.reward_external() + *internal);
  trace.clear_cluster_id();
  trace.clear_replay_count();
  return trace;
}

// Step 3 for one batch of seqs: read from the old fleet, re-encode, upload
// to the new one, and write the batch's last seq down.
absl::Status MigrateBatch(const MigrationOptions& options,
                          client::Client& client,
                          const ObservationSource& source,
                          const Encoder& encoder, RobotStore& store,
                          const std::vector<SourceIndex>& batch,
                          MigrationSummary& summary) {
  const std::string robot_id = store.state().robot_id();
  v1::GetTracesRequest asked;
  asked.set_fleet_id(options.from_fleet);
  std::map<uint64_t, uint64_t> index_of;
  for (const SourceIndex& s : batch) {
    v1::TraceKey* key = asked.add_keys();
    key->set_robot_id(robot_id);
    key->set_seq(s.seq);
    index_of[s.seq] = s.index;
  }
  absl::StatusOr<v1::GetTracesResponse> held = client.GetTraces(asked);
  if (!held.ok()) return held.status();
  std::vector<v1::MemoryTrace> traces;
  for (const v1::MemoryTrace& old : held->traces()) {
    absl::StatusOr<v1::MemoryTrace> trace =
        Reencode(options, source, encoder, old, index_of.at(old.seq()));
    if (!trace.ok()) return trace.status();
    traces.push_back(*std::move(trace));
  }
  uint64_t accepted = 0, duplicates = 0;
  if (!traces.empty()) {
    absl::StatusOr<v1::UploadTracesResponse> sent =
        client.Upload(options.to_fleet, traces);
    if (!sent.ok()) return sent.status();
    accepted = sent->accepted();
    duplicates = sent->duplicates();
  }
  const uint64_t missing = uint64_t(held->missing_size());
  absl::Status written = store.Update([&](RobotState& state) {
    state.set_migrated_through_seq(batch.back().seq);
    state.set_traces_migrated(state.traces_migrated() + accepted + duplicates);
  });
  if (!written.ok()) return written;
  summary.migrated += accepted + duplicates;
  summary.duplicates += duplicates;
  summary.not_held += missing;
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<MigrationSummary> MigrateRobot(const MigrationOptions& options,
                                              client::Client& client,
                                              const ObservationSource& source,
                                              const Encoder& encoder,
                                              RobotStore& store) {
  MigrationSummary summary;
  const RobotState start = store.state();
  if (start.fleet_id() == options.to_fleet) {
    summary.already_done = true;
    return summary;
  }
  if (start.fleet_id() != options.from_fleet) {
    return absl::FailedPreconditionError(
        absl::StrCat("the data dir holds robot \"", start.robot_id(),
                     "\" of fleet \"", start.fleet_id(), "\", neither \"",
                     options.from_fleet, "\" nor \"", options.to_fleet, "\""));
  }
  // A migration to another fleet than the one under way starts over.
  if (start.migrating_to() != options.to_fleet) {
    absl::Status begun = store.Update([&](RobotState& state) {
      state.set_migrating_to(options.to_fleet);
      state.set_migrated_through_seq(0);
      state.set_traces_migrated(0);
    });
    if (!begun.ok()) return begun;
  }
  if (absl::Status sent = SendQueue(options, client, store, summary);
      !sent.ok()) {
    return Stopped(sent, "uploading the queue to the old fleet", summary);
  }
  summary.open_discarded = store.queue().open_segment;
  if (absl::Status discarded = store.DiscardOpenSegment(); !discarded.ok()) {
    return discarded;
  }
  Say(options,
      absl::StrFormat("migrating from fleet %s to %s (encoder %s): %d queued "
                      "traces sent to %s first, %d open observations to be "
                      "made again, resuming after seq %d",
                      options.from_fleet, options.to_fleet, encoder.version(),
                      summary.queued_sent, options.from_fleet,
                      summary.open_discarded,
                      store.state().migrated_through_seq()));
  uint64_t with_source = 0;
  for (uint64_t after = 0;;) {
    absl::StatusOr<std::vector<SourceIndex>> batch =
        store.SourceIndices(after, options.batch);
    if (!batch.ok()) return batch.status();
    if (batch->empty()) break;
    with_source += batch->size();
    after = batch->back().seq;
    if (after <= store.state().migrated_through_seq()) continue;  // done
    std::erase_if(*batch, [&](const SourceIndex& s) {
      return s.seq <= store.state().migrated_through_seq();
    });
    if (absl::Status moved = MigrateBatch(options, client, source, encoder,
                                          store, *batch, summary);
        !moved.ok()) {
      return Stopped(moved, absl::StrCat("at seq ", batch->front().seq),
                     summary);
    }
    Say(options, absl::StrFormat("migrated through seq %d: %d traces so far",
                                 after, store.state().traces_migrated()));
  }
  const RobotState state = store.state();
  summary.no_source = state.traces_queued() - with_source;
  summary.migrated = state.traces_migrated();
  absl::Status moved = store.Update([&](RobotState& next) {
    next.set_fleet_id(options.to_fleet);
    next.set_migrating_to("");
    next.set_traces_not_migrated(summary.no_source);
    // The watch cursor is an event id of the old fleet.
    next.set_watch_cursor(0);
  });
  if (!moved.ok()) return moved;
  return summary;
}

}  // namespace fleetmem::robot
