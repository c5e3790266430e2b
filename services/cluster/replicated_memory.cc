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

ReplicatedMemory::ReplicatedMemory(std::string self, size_t max_entry_bytes,
                                   uint64_t max_backlog_traces,
                                   engine::QuotaOptions rates,
                                   std::unique_ptr<NatsFleetLog> log,
                                   transport::PeerOptions peers,
                                   engine::MemoryEngine* engine,
                                   ClusterNodeOptions node)
    : self_(std::move(self)),
      max_entry_bytes_(max_entry_bytes),
      max_backlog_traces_(max_backlog_traces),
      rates_(std::move(rates),
             [] {
               return std::chrono::duration<double>(
                          std::chrono::steady_clock::now().time_since_epoch())
                   .count();
             }),
      engine_(engine),
      log_(std::move(log)),
      forwarder_(std::move(peers)),
      node_(std::move(node), log_.get(), log_.get(), log_.get(), engine) {}

ReplicatedMemory::~ReplicatedMemory() { Shutdown(); }

void ReplicatedMemory::Run(std::function<void(const std::string&)> lost) {
  if (lost) node_.OnFleetLost(std::move(lost));
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
  // The fleet's shape (from its log), so that an acknowledged upload is
  // never one its owner cannot apply.
  absl::StatusOr<std::optional<engine::FleetShape>> shape = ShapeOf(fleet_id);
  if (!shape.ok()) return shape.status();
  engine::UploadQuota& limits = engine_->quota();
  const size_t max_traces = engine_->options().max_traces_per_upload;
  absl::Status valid =
      engine::AdmitShape(limits, fleet_id, traces,
                         shape->has_value() ? &**shape : nullptr, max_traces);
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
    // The fleets as the log lists them now (creations are rare; the last
    // round's listing may be a round old). Two replicas creating fleets at
    // the same moment may both pass: max_fleets can be passed by as many
    // fleets as are created at once.
    absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
    valid = limits.AdmitNewFleet(
        fleet_id, fleets.ok() ? fleets->size() : node_.fleets_seen());
    if (!valid.ok()) return valid;
    // Appended only as the log's first entry: of two uploads creating the
    // fleet at once with different shapes, the second is checked against
    // the first's shape instead of being acknowledged and refused when
    // applied.
    absl::StatusOr<Ingested> created = Ingest(
        *log_, fleet_id, traces, max_entry_bytes_, /*creates_fleet=*/true);
    if (!absl::IsFailedPrecondition(created.status())) {
      return Answer(fleet_id, created);
    }
    // Created by another upload meanwhile: this one is an upload to it.
    shape = ShapeOf(fleet_id);
    if (!shape.ok()) return shape.status();
    valid =
        engine::AdmitShape(limits, fleet_id, traces,
                           shape->has_value() ? &**shape : nullptr, max_traces);
    if (!valid.ok()) return valid;
  }
  // The fleet's load is its owner's to admit: it alone knows what the fleet
  // holds and what of its log is not applied yet. A fleet without an owner
  // (just created, or its owner's lease expired) is taken here.
  std::string holder;
  if (!Serves(fleet_id) && !TakeIfFree(fleet_id, &holder)) {
    return ForwardUpload(fleet_id, traces, options, holder);
  }
  valid = engine::AdmitLoad(limits, fleet_id, Load(fleet_id),
                            NewTraces(fleet_id, traces), max_backlog_traces_);
  if (!valid.ok()) return valid;
  // Acknowledged at the replicated append: options.wait_applied is not
  // served here (the answer says so: Uploaded::applied stays false).
  return Answer(fleet_id, Ingest(*log_, fleet_id, traces, max_entry_bytes_));
}

absl::StatusOr<transport::Uploaded> ReplicatedMemory::Answer(
    std::string_view fleet_id, const absl::StatusOr<Ingested>& ingested) {
  if (!ingested.ok()) return ingested.status();
  transport::Uploaded uploaded;
  uploaded.result.accepted = ingested->traces - ingested->duplicate_traces;
  uploaded.result.duplicates = ingested->duplicate_traces;
  uploaded.sequence = ingested->last_sequence;
  if (uploaded.result.accepted > 0) {
    absl::MutexLock lock(&load_mu_);
    appended_[std::string(fleet_id)].push_back(
        {ingested->last_sequence, uploaded.result.accepted});
  }
  return uploaded;
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

engine::FleetLoad ReplicatedMemory::Load(std::string_view fleet_id) {
  engine::FleetLoad load;
  load.held = engine_->HeldTraces(fleet_id);
  const uint64_t position = node_.materialiser().Position(fleet_id).value_or(0);
  absl::MutexLock lock(&load_mu_);
  auto it = appended_.find(V(fleet_id));
  if (it == appended_.end()) return load;
  std::deque<AppendedEntry>& entries = it->second;
  while (!entries.empty() && entries.front().sequence <= position) {
    entries.pop_front();
  }
  for (const AppendedEntry& entry : entries) load.backlog += entry.traces;
  if (entries.empty()) appended_.erase(it);
  return load;
}

uint64_t ReplicatedMemory::NewTraces(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces) {
  // Against what the fleet holds applied: a trace still in the log's
  // unapplied tail counts as new here (the owner's limit errs on the safe
  // side) and is a duplicate when applied.
  absl::flat_hash_map<std::string_view, core::SeqSet> seen;
  uint64_t fresh = 0;
  for (const core::MemoryTrace& trace : traces) {
    auto [it, inserted] = seen.try_emplace(trace.robot_id);
    if (inserted) it->second = engine_->Received(fleet_id, trace.robot_id);
    if (it->second.Insert(trace.seq)) ++fresh;
  }
  return fresh;
}

absl::StatusOr<std::optional<engine::FleetShape>> ReplicatedMemory::ShapeOf(
    std::string_view fleet_id) {
  {
    absl::MutexLock lock(&owners_mu_);
    auto it = shapes_.find(std::string(fleet_id));
    if (it != shapes_.end()) return it->second;
  }
  absl::StatusOr<std::optional<engine::FleetShape>> shape =
      FleetShapeFromLog(*log_, log_.get(), fleet_id);
  if (!shape.ok() || !shape->has_value()) return shape;
  absl::MutexLock lock(&owners_mu_);
  shapes_[std::string(fleet_id)] = **shape;
  return shape;
}

absl::StatusOr<std::optional<std::string>> ReplicatedMemory::Owner(
    std::string_view fleet_id) {
  if (node_.materialiser().Owns(fleet_id)) return std::nullopt;
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
      // Taken by this replica's loop a moment ago.
      return std::nullopt;
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
    std::string_view request_id) {
  // Checked before it is logged, as in embedded mode (EmbeddedMemory).
  if (absl::Status valid =
          engine_->CheckSampleReplay(fleet_id, robot_id, count, request_id);
      !valid.ok()) {
    return valid;
  }
  return node_.materialiser().SampleReplay(fleet_id, robot_id, count,
                                           request_id);
}

}  // namespace fleetmem::cluster
