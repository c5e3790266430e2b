#include "services/cluster/replicated_memory.h"

#include <algorithm>
#include <chrono>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "proto/convert/trace_convert.h"
#include "services/cluster/materialiser.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/engine/admission.h"

namespace fleetmem::cluster {

namespace {

// The owner's write path: embedded mode's, over the replicated log (no
// appliers: the Materialiser applies).
std::unique_ptr<engine::WritePath> OwnerWrites(engine::MemoryEngine* engine,
                                               engine::FleetLog* log,
                                               uint64_t max_backlog_traces,
                                               size_t max_entry_bytes) {
  engine::WritePathOptions options;
  options.max_backlog_traces = max_backlog_traces;
  options.replicated = engine::WritePathOptions::Replicated{
      [max_entry_bytes](std::span<const core::MemoryTrace> traces) {
        return CutUpload(traces, max_entry_bytes);
      }};
  // Only the options above differ from the defaults, which are valid.
  return *engine::WritePath::Open(std::move(options), engine, log);
}

}  // namespace

ReplicatedMemory::ReplicatedMemory(std::string self, size_t max_entry_bytes,
                                   uint64_t max_backlog_traces,
                                   engine::QuotaOptions rates,
                                   std::unique_ptr<NatsFleetLog> log,
                                   transport::PeerOptions peers,
                                   engine::MemoryEngine* engine,
                                   ClusterNodeOptions node)
    : self_(std::move(self)),
      max_entry_bytes_(max_entry_bytes),
      rates_(std::move(rates),
             [] {
               return std::chrono::duration<double>(
                          std::chrono::steady_clock::now().time_since_epoch())
                   .count();
             }),
      engine_(engine),
      log_(std::move(log)),
      writes_(
          OwnerWrites(engine, log_.get(), max_backlog_traces, max_entry_bytes)),
      forwarder_(std::move(peers)),
      node_(WithCallsThroughTheWritePath(std::move(node)), log_.get(),
            log_.get(), log_.get(), engine) {}

ClusterNodeOptions ReplicatedMemory::WithCallsThroughTheWritePath(
    ClusterNodeOptions node) {
  // The Materialiser appends a call (holding the fleet's lease) through
  // the owner's write path, after the uploads acknowledged before it.
  node.materialiser.append_call =
      [this](std::string_view fleet_id,
             const engine::LogRecord& record) -> absl::StatusOr<uint64_t> {
    const std::optional<uint64_t> position =
        node_.materialiser().Position(fleet_id);
    if (position.has_value()) {
      if (absl::Status owned = writes_->Own(fleet_id, *position); !owned.ok()) {
        // Not FAILED_PRECONDITION, which says "not the owner" to the caller.
        return absl::UnavailableError(
            absl::StrCat("fleet \"", V(fleet_id), "\": ", owned.message(),
                         "; the call was not logged: retry"));
      }
    }
    absl::StatusOr<engine::Appended> appended =
        writes_->AppendCall(fleet_id, record);
    if (!appended.ok()) return appended.status();
    return appended->sequence;
  };
  return node;
}

ReplicatedMemory::~ReplicatedMemory() {
  Shutdown();
  writes_->Stop();
}

void ReplicatedMemory::Run(std::function<void(const std::string&)> lost) {
  // A fleet lost ends its write path here first: uploads queued for it are
  // refused (retry: the new owner admits them).
  node_.OnFleetLost([this, lost = std::move(lost)](const std::string& fleet) {
    writes_->Disown(fleet);
    if (lost) lost(fleet);
  });
  node_.Start();
}

void ReplicatedMemory::Shutdown() {
  if (shut_down_) return;
  shut_down_ = true;
  node_.Stop();
  node_.ReleaseAll();
}

absl::StatusOr<transport::Uploaded> ReplicatedMemory::Upload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    const transport::UploadOptions& options) {
  // The fleet's shape (from its log), so that an upload is rated, and
  // forwarded, only if its owner can admit it.
  absl::StatusOr<std::optional<engine::FleetShape>> shape = ShapeOf(fleet_id);
  if (!shape.ok()) return shape.status();
  engine::UploadQuota& limits = engine_->quota();
  const size_t max_traces = engine_->options().max_traces_per_upload;
  absl::Status valid =
      engine::AdmitShape(limits, fleet_id, traces,
                         shape->has_value() ? &**shape : nullptr, max_traces);
  if (!valid.ok() && shape->has_value()) {
    // The shape this replica read before may be a deleted fleet's: read
    // the log again (only when an upload does not fit it).
    shape = ShapeOf(fleet_id, /*fresh=*/true);
    if (!shape.ok()) return shape.status();
    valid =
        engine::AdmitShape(limits, fleet_id, traces,
                           shape->has_value() ? &**shape : nullptr, max_traces);
  }
  if (!valid.ok()) return valid;
  if (traces.empty()) return transport::Uploaded{};
  // Rates are the receiving replica's (a forwarded upload was rated there).
  if (!options.forwarded) {
    if (absl::Status admitted = rates_.AdmitRates(fleet_id, traces);
        !admitted.ok()) {
      return admitted;
    }
  }
  if (!shape->has_value()) {
    absl::StatusOr<transport::Uploaded> created = Create(fleet_id, traces);
    if (!absl::IsFailedPrecondition(created.status())) return created;
    // Created by another upload meanwhile: this one is an upload to it.
    shape = ShapeOf(fleet_id);
    if (!shape.ok()) return shape.status();
    valid =
        engine::AdmitShape(limits, fleet_id, traces,
                           shape->has_value() ? &**shape : nullptr, max_traces);
    if (!valid.ok()) return valid;
  }
  // The fleet's owner admits and appends: it alone knows what the fleet
  // holds and what of its log is not applied yet. A fleet without an owner
  // (just created, or its owner's lease expired) is taken here.
  std::string holder;
  if (!Serves(fleet_id) && !TakeIfFree(fleet_id, &holder)) {
    return ForwardUpload(fleet_id, traces, options, holder);
  }
  const std::span<const core::MemoryTrace> one[] = {traces};
  return std::move(Write(fleet_id, one).front());
}

absl::StatusOr<transport::Uploaded> ReplicatedMemory::Create(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces) {
  // The fleets as the log lists them now (creations are rare; the last
  // round's listing may be a round old). Two replicas creating fleets at
  // the same moment may both pass: max_fleets can be passed by as many
  // fleets as are created at once.
  if (absl::Status valid = engine_->quota().AdmitCreationByUpload(fleet_id);
      !valid.ok()) {
    return valid;
  }
  absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
  if (absl::Status valid = engine_->quota().AdmitNewFleet(
          fleet_id, fleets.ok() ? fleets->size() : node_.fleets_seen());
      !valid.ok()) {
    return valid;
  }
  // Appended only as the log's first entry: of two uploads creating the
  // fleet at once with different shapes, the second is checked against
  // the first's shape instead of being acknowledged and refused when
  // applied.
  absl::StatusOr<Ingested> ingested =
      Ingest(*log_, fleet_id, traces, max_entry_bytes_,
             /*creates_fleet=*/true);
  if (!ingested.ok()) return ingested.status();
  transport::Uploaded uploaded;
  uploaded.result.accepted = ingested->traces - ingested->duplicate_traces;
  uploaded.result.duplicates = ingested->duplicate_traces;
  uploaded.sequence = ingested->last_sequence;
  return uploaded;
}

std::vector<absl::StatusOr<transport::Uploaded>> ReplicatedMemory::UploadMany(
    std::string_view fleet_id,
    std::span<const std::span<const core::MemoryTrace>> messages,
    const transport::UploadOptions& options) {
  // The owner writes a stream's waiting messages in one group commit (one
  // round trip to JetStream for all), as embedded mode does; elsewhere
  // (forwarding, a fleet's creation) they go one after another.
  absl::StatusOr<std::optional<engine::FleetShape>> shape = ShapeOf(fleet_id);
  if (messages.size() < 2 || !Serves(fleet_id) || !shape.ok() ||
      !shape->has_value()) {
    return FleetMemory::UploadMany(fleet_id, messages, options);
  }
  // Checked and rated here one by one, as Upload does; the first refused
  // ends the call (the rest ABORTED, as FleetMemory::UploadMany).
  size_t admitted = 0;
  absl::Status refused;
  for (; admitted < messages.size(); ++admitted) {
    refused =
        engine::AdmitShape(engine_->quota(), fleet_id, messages[admitted],
                           &**shape, engine_->options().max_traces_per_upload);
    if (!refused.ok() && admitted == 0) {
      // Upload checks the shape again (a deleted fleet's, read before).
      return FleetMemory::UploadMany(fleet_id, messages, options);
    }
    if (refused.ok() && !options.forwarded) {
      refused = rates_.AdmitRates(fleet_id, messages[admitted]);
    }
    if (!refused.ok()) break;
  }
  std::vector<absl::StatusOr<transport::Uploaded>> results;
  if (admitted > 0) results = Write(fleet_id, messages.first(admitted));
  if (admitted < messages.size()) results.push_back(refused);
  while (results.size() < messages.size()) {
    results.push_back(absl::AbortedError(
        "not stored: an upload before it in the same call was refused"));
  }
  return results;
}

std::vector<absl::StatusOr<transport::Uploaded>> ReplicatedMemory::Write(
    std::string_view fleet_id,
    std::span<const std::span<const core::MemoryTrace>> messages) {
  const std::optional<uint64_t> position =
      node_.materialiser().Position(fleet_id);
  absl::Status owned = position.has_value()
                           ? writes_->Own(fleet_id, *position)
                           : absl::FailedPreconditionError(absl::StrCat(
                                 "not owned by \"", self_, "\" any more"));
  if (!owned.ok()) {
    // Lost meanwhile, or its log cannot be read back: another replica or a
    // retry writes it.
    return std::vector<absl::StatusOr<transport::Uploaded>>(
        messages.size(),
        absl::UnavailableError(absl::StrCat(
            "fleet \"", V(fleet_id), "\": ", owned.message(),
            " (ownership moved); nothing of this upload was stored: retry")));
  }
  // The write path began with this ownership (the log's unapplied tail
  // read back once); it learns how far the owner has applied.
  writes_->Applied(fleet_id, *position);
  std::vector<absl::StatusOr<engine::Appended>> appended =
      writes_->AppendMany(fleet_id, messages);
  std::vector<absl::StatusOr<transport::Uploaded>> results;
  for (size_t i = 0; i < messages.size(); ++i) {
    FLEETMEM_LOG(kDebug) << "cluster: fleet \"" << fleet_id << "\": upload of "
                         << messages[i].size() << " traces (robot \""
                         << (messages[i].empty() ? "" : messages[i][0].robot_id)
                         << "\", seq "
                         << (messages[i].empty() ? 0 : messages[i][0].seq)
                         << "..) "
                         << (appended[i].ok()
                                 ? absl::StrCat(
                                       "accepted ", appended[i]->accepted,
                                       ", duplicates ", appended[i]->duplicates,
                                       ", entry ", appended[i]->sequence)
                                 : appended[i].status().ToString());
    if (!appended[i].ok()) {
      results.push_back(appended[i].status());
      continue;
    }
    transport::Uploaded uploaded;
    uploaded.result.accepted = appended[i]->accepted;
    uploaded.result.duplicates = appended[i]->duplicates;
    uploaded.sequence = appended[i]->sequence;
    results.push_back(uploaded);
  }
  return results;
}

absl::StatusOr<transport::Uploaded> ReplicatedMemory::ForwardUpload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    const transport::UploadOptions& options, const std::string& holder) {
  if (options.forwarded) {
    return absl::UnavailableError(absl::StrCat(
        "fleet \"", V(fleet_id), "\" is not owned by \"", self_,
        "\" (ownership moved); nothing of this upload was stored: retry"));
  }
  // The holder TakeIfFree read; Owner() (the last owner seen) when it could
  // not read one.
  absl::StatusOr<std::optional<std::string>> owner =
      holder.empty() ? Owner(fleet_id)
                     : absl::StatusOr<std::optional<std::string>>(holder);
  if (!owner.ok()) return owner.status();
  if (!owner->has_value()) {
    return absl::UnavailableError(absl::StrCat(
        "fleet \"", V(fleet_id),
        "\" is being taken by this replica; nothing of this upload was "
        "stored: retry"));
  }
  v1::UploadTracesRequest request;
  request.set_fleet_id(std::string(fleet_id));
  for (const core::MemoryTrace& trace : traces) {
    api::TraceToProto(trace, request.add_traces());
  }
  v1::UploadTracesResponse response;
  if (absl::Status forwarded = forwarder_.Forward(
          **owner, "UploadTraces", request, &response, options.deadline);
      !forwarded.ok()) {
    return forwarded;
  }
  transport::Uploaded uploaded;
  uploaded.result.accepted = response.accepted();
  uploaded.result.duplicates = response.duplicates();
  uploaded.sequence = response.last_sequence();
  return uploaded;
}

bool ReplicatedMemory::TakeIfFree(std::string_view fleet_id,
                                  std::string* holder) {
  absl::StatusOr<std::optional<Lease>> lease = log_->Holder(fleet_id);
  if (!lease.ok()) return false;
  if (lease->has_value()) {
    if ((*lease)->owner != self_) *holder = (*lease)->owner;
    return false;
  }
  // Takes the lease and applies a first batch of the log, as the ownership
  // loop does for a free fleet (which balances the fleets later).
  return node_.materialiser().Step(fleet_id).ok();
}

absl::StatusOr<std::optional<engine::FleetShape>> ReplicatedMemory::ShapeOf(
    std::string_view fleet_id, bool fresh) {
  {
    absl::MutexLock lock(&owners_mu_);
    auto it = shapes_.find(std::string(fleet_id));
    if (it != shapes_.end()) {
      if (!fresh) return it->second;
      shapes_.erase(it);
    }
  }
  absl::StatusOr<std::optional<engine::FleetShape>> shape =
      FleetShapeFromLog(*log_, log_.get(), fleet_id);
  if (!shape.ok() || !shape->has_value()) return shape;
  absl::MutexLock lock(&owners_mu_);
  shapes_[std::string(fleet_id)] = **shape;
  return shape;
}

absl::Status ReplicatedMemory::Catching(
    std::string_view fleet_id,
    const std::optional<Materialiser::TakeProgress>& progress) {
  if (!progress.has_value()) {
    return absl::UnavailableError(
        absl::StrCat("fleet \"", V(fleet_id), "\" is being taken by replica \"",
                     self_, "\"; retry"));
  }
  return absl::UnavailableError(
      absl::StrCat("fleet \"", V(fleet_id), "\" was taken by replica \"", self_,
                   "\" a moment ago and is applied through entry ",
                   progress->applied, " of the ", progress->end_at_take,
                   " logged before; it is served once they are: retry"));
}

absl::StatusOr<std::optional<std::string>> ReplicatedMemory::Owner(
    std::string_view fleet_id) {
  if (std::optional<Materialiser::TakeProgress> held =
          node_.materialiser().Progress(fleet_id)) {
    if (held->caught_up()) return std::nullopt;
    return Catching(fleet_id, *held);
  }
  absl::StatusOr<std::optional<Lease>> holder = log_->Holder(fleet_id);
  if (!holder.ok()) {
    // NATS cannot say now (a JetStream leader election): the last owner
    // seen answers, or says the fleet moved.
    absl::MutexLock lock(&owners_mu_);
    auto it = last_owner_.find(std::string(fleet_id));
    if (it != last_owner_.end() && it->second != self_) return it->second;
    return holder.status();
  }
  if (holder->has_value()) {
    {
      absl::MutexLock lock(&owners_mu_);
      last_owner_[std::string(fleet_id)] = (*holder)->owner;
    }
    if ((*holder)->owner == self_) {
      // Taken by this replica's loop a moment ago (or held from before a
      // restart): served once the take has caught up.
      const std::optional<Materialiser::TakeProgress> held =
          node_.materialiser().Progress(fleet_id);
      if (held.has_value() && held->caught_up()) return std::nullopt;
      return Catching(fleet_id, held);
    }
    return (*holder)->owner;
  }
  absl::StatusOr<engine::LogBounds> bounds = log_->Bounds(fleet_id);
  if (!bounds.ok()) return bounds.status();
  // No log: the fleet does not exist, which this replica says as well as
  // any.
  if (bounds->last == 0) return std::nullopt;
  return absl::UnavailableError(absl::StrCat(
      "fleet \"", V(fleet_id),
      "\" has no owner right now (its owner was lost; another replica takes "
      "it once the lease expires); retry"));
}

absl::StatusOr<std::vector<std::pair<std::string, std::string>>>
ReplicatedMemory::Fleets() {
  // While NATS cannot answer (a JetStream leader election), the last
  // listing and the last owners seen answer, as Owner does.
  absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
  {
    absl::MutexLock lock(&owners_mu_);
    if (fleets.ok()) {
      known_fleets_ = *fleets;
    } else if (!known_fleets_.empty()) {
      fleets = known_fleets_;
    }
  }
  if (!fleets.ok()) return fleets.status();
  std::vector<std::pair<std::string, std::string>> owners;
  for (const std::string& fleet : *fleets) {
    std::string owner;
    if (node_.materialiser().Owns(fleet)) {
      owner = self_;
    } else {
      absl::StatusOr<std::optional<Lease>> holder = log_->Holder(fleet);
      absl::MutexLock lock(&owners_mu_);
      if (holder.ok() && holder->has_value()) {
        owner = (*holder)->owner;
        last_owner_[fleet] = owner;
      } else if (!holder.ok()) {
        auto last = last_owner_.find(fleet);
        if (last == last_owner_.end()) return holder.status();
        owner = last->second;
      }
    }
    owners.emplace_back(fleet, std::move(owner));
  }
  return owners;
}

absl::Status ReplicatedMemory::Forward(const std::string& address,
                                       std::string_view method,
                                       const google::protobuf::Message& request,
                                       google::protobuf::Message* response,
                                       absl::Time deadline) {
  return forwarder_.Forward(address, method, request, response, deadline);
}

std::vector<absl::Status> ReplicatedMemory::ForwardEach(
    std::span<const std::string> addresses, std::string_view method,
    const google::protobuf::Message& request,
    std::span<google::protobuf::Message* const> responses,
    absl::Time deadline) {
  std::vector<transport::PeerCall> calls;
  for (size_t i = 0; i < addresses.size(); ++i) {
    calls.push_back({addresses[i], responses[i]});
  }
  return forwarder_.ForwardEach(calls, method, request, deadline);
}

engine::Backlog ReplicatedMemory::Backlog(std::string_view fleet_id) {
  engine::Backlog backlog;
  for (const auto& [owned, position] : node_.materialiser().Positions()) {
    if (owned != fleet_id) continue;
    absl::StatusOr<engine::LogBounds> bounds = log_->Bounds(fleet_id);
    if (!bounds.ok()) break;
    backlog.applied_through = position;
    backlog.appended_through = std::max(bounds->last, position);
    backlog.entries = backlog.appended_through - position;
  }
  return backlog;
}

std::vector<std::pair<std::string, double>> ReplicatedMemory::LogLag() {
  std::vector<std::pair<std::string, double>> lag;
  for (const auto& [fleet_id, position] : node_.materialiser().Positions()) {
    absl::StatusOr<engine::LogBounds> bounds = log_->Bounds(fleet_id);
    if (!bounds.ok()) continue;
    lag.emplace_back(fleet_id, static_cast<double>(bounds->last > position
                                                       ? bounds->last - position
                                                       : 0));
  }
  return lag;
}

absl::StatusOr<engine::ConsolidateResult> ReplicatedMemory::Consolidate(
    std::string_view fleet_id) {
  return node_.materialiser().Consolidate(fleet_id);
}

absl::StatusOr<std::vector<core::MemoryTrace>> ReplicatedMemory::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, uint64_t count,
    std::string_view request_id, const core::ReadFilter* filter) {
  // Checked before it is logged, as in embedded mode (EmbeddedMemory).
  if (absl::Status valid = engine_->CheckSampleReplay(fleet_id, robot_id, count,
                                                      request_id, filter);
      !valid.ok()) {
    return valid;
  }
  return node_.materialiser().SampleReplay(fleet_id, robot_id, count,
                                           request_id, filter);
}

absl::StatusOr<engine::AppliedRecord> ReplicatedMemory::Call(
    std::string_view fleet_id, const engine::LogRecord& call) {
  absl::StatusOr<engine::AppliedRecord> applied =
      node_.materialiser().Call(fleet_id, call);
  if (applied.ok() && std::holds_alternative<engine::DeleteFleetRecord>(call)) {
    absl::MutexLock lock(&owners_mu_);
    shapes_.erase(std::string(fleet_id));  // the next fleet may differ
  }
  return applied;
}

absl::Status ReplicatedMemory::CreateFleet(
    std::string_view fleet_id, const engine::CreateFleetRecord& create) {
  // Read afresh: a shape this replica read before may be a deleted fleet's.
  absl::StatusOr<std::optional<engine::FleetShape>> shape =
      ShapeOf(fleet_id, /*fresh=*/true);
  if (!shape.ok()) return shape.status();
  const absl::Status exists = absl::AlreadyExistsError(absl::StrCat(
      "fleet \"", V(fleet_id),
      "\" exists already (made by CreateFleet or its first upload); "
      "UpdateFleet changes its settings"));
  if (shape->has_value()) return exists;
  absl::Status valid =
      engine_->quota().AdmitDimension(fleet_id, create.code_dimension);
  if (valid.ok()) {
    absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
    valid = engine_->quota().AdmitNewFleet(
        fleet_id, fleets.ok() ? fleets->size() : node_.fleets_seen());
  }
  if (!valid.ok()) return valid;
  // Only as the log's first entry: of two creations (or a creation and a
  // first upload) at once, one makes the fleet. The id makes a retry of a
  // lost answer a duplicate.
  const std::string id = absl::StrCat("create-fleet:", V(fleet_id));
  const engine::LogAppend append{create, id};
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log_->Append(fleet_id, {&append, 1}, {.only_first = true});
  if (absl::IsFailedPrecondition(appended.status())) return exists;
  if (!appended.ok()) return appended.status();
  // Applied by whichever replica takes the fleet: this one if none holds
  // it, so that a GetFleet right after finds it here.
  std::string holder;
  if (Serves(fleet_id) || TakeIfFree(fleet_id, &holder)) {
    absl::StatusOr<StepResult> caught_up =
        node_.materialiser().CatchUp(fleet_id);
    if (!caught_up.ok()) return caught_up.status();
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::cluster
