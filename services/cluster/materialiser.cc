#include "services/cluster/materialiser.h"

#include <algorithm>
#include <map>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "proto/convert/trace_convert.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/engine/admission.h"
#include "services/storage/fleet_image.h"

namespace fleetmem::cluster {

namespace {

// The fleet's latest snapshot, decoded: its description and image, or why
// not (DATA_LOSS for one that vanished or does not decode).
absl::StatusOr<std::pair<SnapshotInfo, engine::FleetImage>> FetchImage(
    SnapshotStore& snapshots, std::string_view fleet_id) {
  absl::StatusOr<std::optional<std::pair<SnapshotInfo, std::string>>> fetched =
      snapshots.Fetch(fleet_id);
  if (!fetched.ok()) return fetched.status();
  if (!fetched->has_value()) {
    return absl::DataLossError("the snapshot vanished");
  }
  absl::StatusOr<engine::FleetImage> image =
      storage::DecodeFleetImage(fleet_id, (*fetched)->second);
  if (!image.ok()) return image.status();
  return std::make_pair((*fetched)->first, *std::move(image));
}

}  // namespace

absl::StatusOr<std::string> UploadId(
    std::span<const core::MemoryTrace> traces) {
  if (traces.empty()) {
    return absl::InvalidArgumentError("cluster: an empty upload");
  }
  uint64_t first = traces.front().seq, last = first;
  for (const core::MemoryTrace& trace : traces) {
    if (trace.robot_id != traces.front().robot_id) {
      return absl::InvalidArgumentError(
          "cluster: one log entry holds one robot's traces");
    }
    first = std::min(first, trace.seq);
    last = std::max(last, trace.seq);
  }
  // Robot ids are [A-Za-z0-9._:-]; the length keeps "a:1" + seqs apart
  // from "a" + ":1…".
  return absl::StrCat("upload/", traces.front().robot_id.size(), "/",
                      traces.front().robot_id, "/", first, "-", last);
}

absl::StatusOr<std::vector<engine::LogPiece>> CutUpload(
    std::span<const core::MemoryTrace> traces, size_t max_entry_bytes) {
  // Each robot's traces in the order given, robots in order of first sight.
  std::vector<std::string> robots;
  std::map<std::string, std::vector<const core::MemoryTrace*>, std::less<>>
      by_robot;
  for (const core::MemoryTrace& trace : traces) {
    auto [it, added] = by_robot.try_emplace(trace.robot_id);
    if (added) robots.push_back(trace.robot_id);
    it->second.push_back(&trace);
  }
  std::vector<engine::LogPiece> pieces;
  for (const std::string& robot : robots) {
    std::vector<core::MemoryTrace> entry;
    size_t bytes = 0;
    for (const core::MemoryTrace* trace : by_robot[robot]) {
      ::fleetmem::v1::MemoryTrace encoded;
      api::TraceToProto(*trace, &encoded);
      // A repeated field's element: its size, a tag and a length prefix.
      const size_t size = encoded.ByteSizeLong() + 8;
      if (size + 16 > max_entry_bytes) {
        return absl::InvalidArgumentError(
            absl::StrCat("cluster: trace (\"", robot, "\", ", trace->seq,
                         ") takes ", size, " bytes, more than a log entry's ",
                         max_entry_bytes, "; nothing was appended"));
      }
      if (!entry.empty() && bytes + size + 16 > max_entry_bytes) {
        pieces.push_back({std::move(entry), ""});
        entry.clear();
        bytes = 0;
      }
      entry.push_back(*trace);
      bytes += size;
    }
    if (!entry.empty()) pieces.push_back({std::move(entry), ""});
  }
  for (engine::LogPiece& piece : pieces) {
    absl::StatusOr<std::string> id = UploadId(piece.traces);
    if (!id.ok()) return id.status();
    piece.id = *std::move(id);
  }
  return pieces;
}

absl::StatusOr<Ingested> Ingest(engine::FleetLog& log,
                                std::string_view fleet_id,
                                std::span<const core::MemoryTrace> traces,
                                size_t max_entry_bytes, bool creates_fleet) {
  // Entries cut before anything is appended, so a trace too large for one
  // changes nothing.
  absl::StatusOr<std::vector<engine::LogPiece>> entries =
      CutUpload(traces, max_entry_bytes);
  if (!entries.ok()) return entries.status();
  Ingested ingested;
  for (const engine::LogPiece& piece : *entries) {
    const std::vector<core::MemoryTrace>& entry = piece.traces;
    const engine::LogAppend append{engine::UploadRecord{entry}, piece.id};
    absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
        log.Append(fleet_id, {&append, 1},
                   {.only_first = creates_fleet && ingested.entries == 0});
    if (absl::IsFailedPrecondition(appended.status())) {
      return appended.status();  // the first entry: nothing appended
    }
    if (!appended.ok()) {
      return absl::Status(
          appended.status().code(),
          absl::StrCat(appended.status().message(), "; the log holds ",
                       ingested.entries, " of this upload's ", entries->size(),
                       " entries (", ingested.traces,
                       " traces); retrying the upload appends the rest"));
    }
    ++ingested.entries;
    if (appended->front().duplicate) {
      ++ingested.duplicate_entries;
      ingested.duplicate_traces += entry.size();
    }
    ingested.traces += entry.size();
    ingested.last_sequence = appended->front().sequence;
  }
  return ingested;
}

absl::StatusOr<std::optional<engine::FleetShape>> FleetShapeFromLog(
    engine::FleetLog& log, SnapshotStore* snapshots,
    std::string_view fleet_id) {
  // The log's first entry while the log holds it: no call to the snapshot
  // stream on the upload path.
  absl::StatusOr<std::vector<engine::LogEntry>> first =
      log.Read(fleet_id, 0, 1);
  const bool trimmed =
      absl::IsOutOfRange(first.status()) ||
      (first.ok() && !first->empty() && first->front().sequence != 1);
  if (trimmed && snapshots != nullptr) {
    absl::StatusOr<std::optional<SnapshotInfo>> latest =
        snapshots->Latest(fleet_id);
    if (!latest.ok()) return latest.status();
    if (latest->has_value() && (*latest)->code_dimension > 0) {
      return engine::FleetShape{(*latest)->code_dimension,
                                (*latest)->encoder_version};
    }
    if (latest->has_value()) {
      // A deleted fleet's snapshot: the fleet is what the log made after
      // it (its first entry since, an upload or a CreateFleet), or none.
      absl::StatusOr<std::vector<engine::LogEntry>> since =
          log.Read(fleet_id, (*latest)->sequence, 1);
      if (!since.ok()) return since.status();
      if (since->empty()) return std::nullopt;
      return engine::ShapeOfEntry(since->front());
    }
  }
  if (!first.ok() && !trimmed) return first.status();
  if (first.ok() && first->empty()) return std::nullopt;
  const std::optional<engine::FleetShape> shape =
      trimmed ? std::nullopt : engine::ShapeOfEntry(first->front());
  if (!shape.has_value()) {
    return absl::DataLossError(absl::StrCat(
        "cluster: the first entry of the log of fleet \"", V(fleet_id),
        "\" is neither an upload nor a CreateFleet",
        trimmed ? " (trimmed, and no snapshot gives its shape)" : ""));
  }
  return shape;
}

Materialiser::Materialiser(MaterialiserOptions options, engine::FleetLog* log,
                           LeaseTable* leases, SnapshotStore* snapshots,
                           engine::MemoryEngine* engine)
    : options_(std::move(options)),
      log_(log),
      leases_(leases),
      snapshots_(snapshots),
      engine_(engine),
      applier_(log, engine) {
  if (snapshots_ != nullptr && options_.snapshot_every > 0) {
    writer_ = std::thread([this] { WriteSnapshots(); });
  }
}

Materialiser::~Materialiser() {
  {
    absl::MutexLock lock(&pending_mu_);
    stopping_ = true;
  }
  if (writer_.joinable()) writer_.join();
}

void Materialiser::WriteSnapshots() {
  while (true) {
    std::string fleet_id;
    Pending pending;
    {
      absl::MutexLock lock(&pending_mu_);
      pending_mu_.Await(absl::Condition(this, &Materialiser::HasWork));
      if (stopping_) return;
      auto next = pending_.begin();
      fleet_id = next->first;
      pending = std::move(next->second);
      pending_.erase(next);
      writing_ = true;
    }
    Store(fleet_id, pending);
    absl::MutexLock lock(&pending_mu_);
    writing_ = false;
  }
}

void Materialiser::Store(const std::string& fleet_id, const Pending& pending) {
  if (absl::Status stored =
          snapshots_->Put(fleet_id, pending.info, pending.image);
      !stored.ok()) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                           << "\": no snapshot through entry "
                           << pending.info.sequence << ": " << stored;
    return;
  }
  if (!options_.trim_log) return;
  if (absl::Status trimmed = log_->Trim(fleet_id, pending.info.sequence);
      !trimmed.ok()) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id << "\": " << trimmed;
  }
}

void Materialiser::WaitForSnapshots() {
  absl::MutexLock lock(&pending_mu_);
  pending_mu_.Await(absl::Condition(this, &Materialiser::Idle));
}

absl::StatusOr<StepResult> Materialiser::Step(std::string_view fleet_id) {
  absl::MutexLock lock(&mu_);
  return StepLocked(fleet_id, 0, nullptr);
}

absl::StatusOr<Materialiser::Owned*> Materialiser::Take(
    std::string_view fleet_id, absl::Time* renewed_at) {
  // Where this replica's own store stands: entries up to it are in its
  // state (an earlier ownership, or before a restart).
  absl::StatusOr<uint64_t> position = engine_->LogPosition(fleet_id);
  if (!position.ok()) return position.status();
  absl::StatusOr<Lease> lease = leases_->Acquire(fleet_id, options_.replica_id);
  if (!lease.ok()) return lease.status();
  // Where the log ends now: what was acknowledged before this take is in
  // it, and reads wait until it is applied (Progress). Unread, the fleet is
  // not taken (the lease is kept: the next step takes it again at once).
  absl::StatusOr<engine::LogBounds> bounds = log_->Bounds(fleet_id);
  if (!bounds.ok()) return bounds.status();
  FLEETMEM_LOG(kInfo) << "cluster: fleet \"" << fleet_id
                      << "\" taken (lease revision " << lease->revision
                      << ", this replica's store at entry " << *position << ")";
  *renewed_at = options_.clock->Now();
  {
    absl::MutexLock held(&lease_mu_);
    held_[std::string(fleet_id)] =
        Held{*lease, *renewed_at, *position, bounds->last};
  }
  Owned taken{*position};
  // Under the lease: a restore is a write like any other.
  if (absl::Status restored = RestoreIfBehind(fleet_id, taken);
      !restored.ok()) {
    // Not owned yet (the lease is kept: the next step takes it again at
    // once, as its holder).
    {
      absl::MutexLock held(&lease_mu_);
      held_.erase(std::string(fleet_id));
    }
    // While the restore ran (seconds, when the snapshot stream elects a
    // leader) this replica held the lease and Owns() said so: watches of
    // the fleet were accepted here. They end now, as for a lost lease;
    // before, they went on unserved (the cluster test's paused owner, 1
    // run in 50: its restore timed out across the pause).
    Lost(fleet_id, absl::Status(restored.code(),
                                absl::StrCat("not restored from its snapshot: ",
                                             restored.message())));
    return restored;
  }
  return &owned_.emplace(std::string(fleet_id), std::move(taken)).first->second;
}

absl::StatusOr<Materialiser::Owned*> Materialiser::Fence(
    std::string_view fleet_id, absl::Time* renewed_at) {
  auto it = owned_.find(fleet_id);
  if (it == owned_.end()) return Take(fleet_id, renewed_at);
  // No entry is applied under a lease this replica lost.
  absl::StatusOr<absl::Time> renewed = RenewIfDue(fleet_id, false);
  if (absl::IsFailedPrecondition(renewed.status())) owned_.erase(it);
  if (!renewed.ok()) return renewed.status();
  *renewed_at = *renewed;
  return &it->second;
}

absl::StatusOr<StepResult> Materialiser::StepLocked(
    std::string_view fleet_id, uint64_t capture,
    engine::AppliedRecord* outcome) {
  absl::Time renewed_at;
  absl::StatusOr<Owned*> fenced = Fence(fleet_id, &renewed_at);
  if (!fenced.ok()) return fenced.status();
  Owned& owned = **fenced;
  StepResult result{0, owned.position, 0, std::exchange(owned.restored, 0), 0};
  if (std::optional<Lease> held = lease(fleet_id)) {
    result.revision = held->revision;
  }
  engine::ApplyHooks hooks;
  // Entries are applied only within two renew intervals of a successful
  // renewal (the lease has a third of its time left then); a longer step
  // ends there and the next renews first. The entry a call waits for is
  // applied in any case.
  hooks.may_apply = [&](const engine::LogEntry& entry) {
    return options_.renew_interval <= absl::ZeroDuration() ||
           options_.clock->Now() - renewed_at < 2 * options_.renew_interval ||
           entry.sequence <= capture;
  };
  // A DeleteFleet applied in this step: snapshot at once, so that the
  // deleted fleet's entries and its earlier snapshot leave JetStream (the
  // snapshot replaces the old one; the log is trimmed through it).
  bool deleted = false;
  hooks.applied = [&](const engine::LogEntry& entry,
                      const engine::AppliedRecord& applied) {
    deleted = deleted ||
              std::holds_alternative<engine::DeleteFleetRecord>(entry.record);
    FLEETMEM_LOG(kDebug) << "cluster: fleet \"" << fleet_id << "\": entry "
                         << entry.sequence << " (" << entry.id
                         << ") applied after " << owned.position;
    if (entry.sequence == capture && outcome != nullptr) *outcome = applied;
    owned.position = entry.sequence;
  };
  absl::StatusOr<engine::AppliedTurn> turn =
      applier_.Turn(fleet_id, owned.position, options_.batch, hooks);
  if (absl::IsOutOfRange(turn.status())) {
    // Trimmed past this replica's position since it took the fleet (the
    // previous owner's snapshot writer, late): restore, then read on.
    if (absl::Status restored = RestoreIfBehind(fleet_id, owned);
        !restored.ok()) {
      return restored;
    }
    result.restored = std::exchange(owned.restored, 0);
    result.position = owned.position;
    turn = applier_.Turn(fleet_id, owned.position, options_.batch, hooks);
  }
  if (!turn.ok()) return turn.status();
  result.applied = turn->applied;
  if (!turn->stopped.ok()) return turn->stopped;
  result.position = owned.position;
  SnapshotIfDue(fleet_id, owned, result, /*now=*/deleted);
  absl::MutexLock held(&lease_mu_);
  if (auto h = held_.find(fleet_id); h != held_.end()) {
    h->second.position = owned.position;
  }
  return result;
}

absl::StatusOr<absl::Time> Materialiser::RenewIfDue(std::string_view fleet_id,
                                                    bool always, bool stopped) {
  absl::MutexLock renewing(&renew_mu_);
  Lease lease;
  absl::Status expired;
  {
    absl::MutexLock held(&lease_mu_);
    auto it = held_.find(fleet_id);
    if (it == held_.end()) {
      return absl::FailedPreconditionError(absl::StrCat(
          "cluster: the lease of fleet \"", V(fleet_id), "\" was lost"));
    }
    const absl::Duration since = options_.clock->Now() - it->second.renewed_at;
    if (!always && since < options_.renew_interval) {
      return it->second.renewed_at;
    }
    if (stopped && since >= options_.lease_ttl) {
      // Expired while this replica was stopped: another may hold it by now.
      held_.erase(it);
      expired = absl::FailedPreconditionError(absl::StrCat(
          "cluster: the lease of fleet \"", V(fleet_id), "\" was not renewed ",
          "for ", absl::FormatDuration(since), ", past its time-to-live of ",
          absl::FormatDuration(options_.lease_ttl),
          " while this replica was stopped: taken as lost"));
    } else {
      lease = it->second.lease;
    }
  }
  if (!expired.ok()) {
    Lost(fleet_id, expired);
    return expired;
  }
  const absl::Time now = options_.clock->Now();
  absl::StatusOr<Lease> renewed = leases_->Renew(lease);
  bool lost = false;
  {
    absl::MutexLock held(&lease_mu_);
    auto it = held_.find(fleet_id);
    if (absl::IsFailedPrecondition(renewed.status())) {
      if (it != held_.end()) {
        held_.erase(it);
        lost = true;
      }
    } else if (renewed.ok()) {
      if (it == held_.end()) {  // released meanwhile
        return absl::FailedPreconditionError(absl::StrCat(
            "cluster: the lease of fleet \"", V(fleet_id), "\" was released"));
      }
      it->second.lease = *std::move(renewed);
      it->second.renewed_at = now;
      return now;
    }
  }
  if (lost) Lost(fleet_id, renewed.status());
  return renewed.status();
}

void Materialiser::Lost(std::string_view fleet_id, const absl::Status& why) {
  FLEETMEM_LOG(kWarning) << "cluster: fleet \"" << fleet_id
                         << "\" lost: " << why.message();
  if (on_lease_lost_) on_lease_lost_(std::string(fleet_id));
}

void Materialiser::RenewLeases() {
  std::vector<std::string> fleets;
  {
    absl::MutexLock held(&lease_mu_);
    for (const auto& [fleet_id, held_lease] : held_) {
      fleets.push_back(fleet_id);
    }
  }
  // This thread waits a fraction of the TTL between calls and does nothing
  // else: a longer gap means the process did not run (it was stopped).
  const bool stopped =
      options_.lease_ttl > absl::ZeroDuration() &&
      renewals_ended_ != absl::InfinitePast() &&
      options_.clock->Now() - renewals_ended_ > options_.lease_ttl;
  for (const std::string& fleet_id : fleets) {
    absl::StatusOr<absl::Time> renewed = RenewIfDue(fleet_id, false, stopped);
    if (!renewed.ok() && !absl::IsFailedPrecondition(renewed.status())) {
      FLEETMEM_LOG(kWarning) << "cluster: " << renewed.status();
    }
  }
  renewals_ended_ = options_.clock->Now();
}

absl::Status Materialiser::RestoreIfBehind(std::string_view fleet_id,
                                           Owned& owned) {
  if (snapshots_ == nullptr) return absl::OkStatus();
  absl::StatusOr<engine::LogBounds> bounds = log_->Bounds(fleet_id);
  if (!bounds.ok()) return bounds.status();
  // The first entry Read can return (1 for a log that never held one).
  const uint64_t* first = &bounds->first;
  if (bounds->last == 0) bounds->first = 1;
  // The log no longer holds every entry after this replica's position.
  const bool trimmed = *first > owned.position + 1;
  // While the log holds every entry needed, a snapshot that cannot be read
  // (its stream electing a leader) or restored is not needed: the log is
  // applied instead.
  auto apply_the_log = [&](const absl::Status& why) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                           << "\": not restored from its snapshot (" << why
                           << "); applying its log from entry "
                           << owned.position + 1;
    return absl::OkStatus();
  };
  absl::StatusOr<std::optional<SnapshotInfo>> latest =
      snapshots_->Latest(fleet_id);
  if (!latest.ok()) {
    return trimmed ? latest.status() : apply_the_log(latest.status());
  }
  if (!latest->has_value() || (trimmed && (*latest)->sequence + 1 < *first)) {
    if (trimmed) {
      // Not trimmed by fleetmem (it trims only what a snapshot covers): a
      // clustered stream skipped its first numbers (proposals that failed
      // as its leader changed: never acknowledged), or an operator purged
      // the log.
      FLEETMEM_LOG(kError)
          << "fleet \"" << fleet_id << "\": its log starts at entry " << *first
          << ", after entry " << owned.position
          << " of this replica, and no snapshot covers the entries between; "
          << "going on from entry " << *first;
      owned.position = *first - 1;
    }
    return absl::OkStatus();
  }
  owned.snapshot = (*latest)->sequence;
  if (owned.snapshot <= owned.position ||
      (!trimmed && owned.snapshot - owned.position < options_.restore_after)) {
    return absl::OkStatus();
  }
  const absl::Time start = absl::Now();
  absl::StatusOr<std::pair<SnapshotInfo, engine::FleetImage>> fetched =
      FetchImage(*snapshots_, fleet_id);
  if (!fetched.ok()) {
    if (!trimmed) return apply_the_log(fetched.status());
    return absl::Status(
        fetched.status().code(),
        absl::StrCat(
            "cluster: fleet \"", V(fleet_id),
            "\" needs its snapshot (its log starts at ", *first,
            ") and it cannot be restored: ", fetched.status().message()));
  }
  // A failed restore may have written the image (its reload failed): the
  // log is not applied over it from the old position; the next step
  // restores again.
  if (absl::Status restored =
          engine_->RestoreFleet(fleet_id, std::move(fetched->second));
      !restored.ok()) {
    return absl::Status(
        restored.code(),
        absl::StrCat("cluster: restoring fleet \"", V(fleet_id),
                     "\" from its snapshot: ", restored.message()));
  }
  const SnapshotInfo& info = fetched->first;
  FLEETMEM_LOG(kInfo) << "fleet \"" << fleet_id
                      << "\" restored from its snapshot through entry "
                      << info.sequence << " (" << info.bytes << " bytes, "
                      << absl::ToDoubleSeconds(absl::Now() - start)
                      << " s); this replica's store was at entry "
                      << owned.position;
  owned.position = info.sequence;
  owned.snapshot = info.sequence;
  owned.restored = info.sequence;
  return absl::OkStatus();
}

void Materialiser::SnapshotIfDue(std::string_view fleet_id, Owned& owned,
                                 StepResult& result, bool now) {
  if (!writer_.joinable() ||
      (!now && owned.position < owned.snapshot + options_.snapshot_every)) {
    return;
  }
  const uint64_t through = owned.position;
  // Tried once per snapshot_every entries, whatever the outcome.
  owned.snapshot = through;
  absl::StatusOr<engine::FleetImage> image =
      engine_->ExportFleet(fleet_id, through);
  absl::Status status = image.status();
  Pending pending;
  if (status.ok()) {
    absl::StatusOr<std::string> bytes = storage::EncodeFleetImage(*image);
    status = bytes.status();
    if (status.ok()) {
      pending.info = SnapshotInfo{through, bytes->size(),
                                  image->record.meta.code_dimension,
                                  image->record.meta.encoder_version};
      pending.image = *std::move(bytes);
    }
  }
  if (!status.ok()) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                           << "\": no snapshot through entry " << through
                           << ": " << status;
    return;
  }
  result.snapshot = through;
  absl::MutexLock lock(&pending_mu_);
  pending_[std::string(fleet_id)] = std::move(pending);
}

absl::StatusOr<StepResult> Materialiser::CatchUp(std::string_view fleet_id) {
  absl::StatusOr<engine::LogBounds> bounds = log_->Bounds(fleet_id);
  if (!bounds.ok()) return bounds.status();
  absl::MutexLock lock(&mu_);
  return StepThroughLocked(fleet_id, bounds->last, nullptr);
}

absl::StatusOr<StepResult> Materialiser::StepThroughLocked(
    std::string_view fleet_id, uint64_t target,
    engine::AppliedRecord* outcome) {
  StepResult total;
  while (true) {
    absl::StatusOr<StepResult> step = StepLocked(fleet_id, target, outcome);
    if (!step.ok()) return step.status();
    total.applied += step->applied;
    total.position = step->position;
    total.revision = step->revision;
    if (step->position >= target) return total;
    if (step->applied == 0) {
      return absl::DataLossError(absl::StrCat(
          "cluster: the log of fleet \"", V(fleet_id), "\" ends at ",
          step->position, ", before sequence ", target));
    }
  }
}

absl::StatusOr<engine::AppliedRecord> Materialiser::Call(
    std::string_view fleet_id, const engine::LogRecord& record) {
  // Held from the append to the entry's application, so that no step
  // applies the entry before this call can capture what it did.
  absl::MutexLock lock(&mu_);
  if (!owned_.contains(fleet_id)) {
    // Routed here as this replica's a moment ago: the fleet was handed over
    // (balancing) or lost since, or is not taken yet. Transient, and nothing
    // was done: UNAVAILABLE, which callers retry (FAILED_PRECONDITION told
    // them not to; the cluster test met it under the sanitizer).
    return absl::UnavailableError(absl::StrCat(
        "cluster: replica \"", options_.replica_id, "\" does not own fleet \"",
        V(fleet_id),
        "\" (not taken yet, or handed over or lost a moment ago); nothing of "
        "this call was logged: retry"));
  }
  absl::StatusOr<uint64_t> sequence = AppendCall(fleet_id, record);
  if (!sequence.ok()) return sequence.status();
  engine::AppliedRecord outcome;
  absl::StatusOr<StepResult> applied =
      StepThroughLocked(fleet_id, *sequence, &outcome);
  if (!applied.ok()) return applied.status();
  if (!outcome.refused.ok()) return outcome.refused;
  return outcome;
}

absl::StatusOr<uint64_t> Materialiser::AppendCall(
    std::string_view fleet_id, const engine::LogRecord& record) {
  if (options_.append_call) return options_.append_call(fleet_id, record);
  // No id: a call is never a retry of another at the log's level.
  const engine::LogAppend append{record};
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log_->Append(fleet_id, {&append, 1}, {});
  if (!appended.ok()) return appended.status();
  return appended->front().sequence;
}

absl::StatusOr<engine::ConsolidateResult> Materialiser::Consolidate(
    std::string_view fleet_id) {
  absl::StatusOr<engine::AppliedRecord> outcome =
      Call(fleet_id, engine::ConsolidateRecord{});
  if (!outcome.ok()) return outcome.status();
  return outcome->consolidated;
}

absl::StatusOr<std::vector<core::MemoryTrace>> Materialiser::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, uint64_t count,
    std::string_view request_id, const core::ReadFilter* filter) {
  absl::StatusOr<engine::AppliedRecord> outcome =
      Call(fleet_id,
           engine::SampleReplayRecord{robot_id, count, request_id, filter});
  if (!outcome.ok()) return outcome.status();
  return std::move(outcome->sample);
}

std::vector<std::pair<std::string, uint64_t>> Materialiser::Positions() const {
  absl::MutexLock lock(&lease_mu_);
  std::vector<std::pair<std::string, uint64_t>> positions;
  for (const auto& [fleet_id, held] : held_) {
    positions.emplace_back(fleet_id, held.position);
  }
  return positions;
}

std::optional<uint64_t> Materialiser::Position(
    std::string_view fleet_id) const {
  absl::MutexLock lock(&lease_mu_);
  auto it = held_.find(fleet_id);
  if (it == held_.end()) return std::nullopt;
  return it->second.position;
}

std::optional<Materialiser::TakeProgress> Materialiser::Progress(
    std::string_view fleet_id) const {
  absl::MutexLock lock(&lease_mu_);
  auto it = held_.find(fleet_id);
  if (it == held_.end()) return std::nullopt;
  return TakeProgress{it->second.position, it->second.end_at_take};
}

bool Materialiser::Owns(std::string_view fleet_id) const {
  absl::MutexLock lock(&lease_mu_);
  return held_.contains(fleet_id);
}

absl::Status Materialiser::Release(std::string_view fleet_id) {
  absl::MutexLock lock(&mu_);
  absl::MutexLock renewing(&renew_mu_);
  owned_.erase(std::string(fleet_id));
  std::optional<Lease> lease;
  {
    absl::MutexLock held(&lease_mu_);
    auto it = held_.find(fleet_id);
    if (it == held_.end()) return absl::OkStatus();
    lease = it->second.lease;
    held_.erase(it);
  }
  return leases_->Release(*lease);
}

std::optional<Lease> Materialiser::lease(std::string_view fleet_id) const {
  absl::MutexLock lock(&lease_mu_);
  auto it = held_.find(fleet_id);
  if (it == held_.end()) return std::nullopt;
  return it->second.lease;
}

}  // namespace fleetmem::cluster
