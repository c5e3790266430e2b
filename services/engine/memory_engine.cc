#include "services/engine/memory_engine.h"

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

absl::Status FleetNotFound(std::string_view fleet_id) {
  return absl::NotFoundError(
      absl::StrCat("fleet \"", V(fleet_id),
                   "\" does not exist (it is created by its first upload)"));
}

std::unique_ptr<PlaceIndex> MemoryEngine::NewIndex(
    size_t dimension, const IndexSettings& index) const {
  if ((index.kind != IndexSettings::Kind::kServer ||
       index.hnsw_codes != IndexSettings::Codes::kServer) &&
      options_.fleet_index_factory) {
    return options_.fleet_index_factory(dimension, index);
  }
  return index_factory_(dimension);
}

const core::MemoryOptions& MemoryEngine::MemoryOptionsFor(
    std::string_view fleet_id) const {
  auto it = options_.fleet_memory.find(fleet_id);
  return it == options_.fleet_memory.end() ? options_.memory : it->second;
}

absl::Status ValidateEngineOptions(const EngineOptions& options) {
  absl::Status status = core::ValidateMemoryOptions(options.memory);
  if (!status.ok()) return status;
  for (const auto& [fleet_id, memory] : options.fleet_memory) {
    status = core::ValidateId("fleet_memory fleet id", fleet_id);
    if (status.ok()) status = core::ValidateMemoryOptions(memory);
    if (!status.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "memory options of fleet \"", V(fleet_id), "\": ", status.message()));
    }
  }
  const std::pair<const char*, size_t> positive[] = {
      {"segment_size", options.segment_size},
      {"max_traces_per_upload", options.max_traces_per_upload},
      {"max_sample_count", options.max_sample_count},
      {"max_keys_per_call", options.max_keys_per_call},
      {"max_query_k", options.max_query_k},
      {"max_query_codes", options.max_query_codes},
      {"max_read_bytes", options.max_read_bytes},
      {"max_events_per_read", options.max_events_per_read},
  };
  for (const auto& [name, value] : positive) {
    if (value == 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("engine option ", name, " must be at least 1"));
    }
  }
  return ValidateQuotaOptions(options.limits);
}

MemoryEngine::MemoryEngine(EngineOptions options, MemoryStore* store,
                           PlaceIndexFactory index_factory, EngineHooks hooks)
    : options_(std::move(options)),
      store_(store),
      index_factory_(std::move(index_factory)),
      hooks_(std::move(hooks)) {
  if (!options_.now_ns) {
    options_.now_ns = [] { return absl::GetCurrentTimeNanos(); };
  }
  if (!options_.now_seconds) {
    options_.now_seconds = [] {
      return std::chrono::duration<double>(
                 std::chrono::steady_clock::now().time_since_epoch())
          .count();
    };
  }
  quota_ = std::make_unique<UploadQuota>(options_.limits, options_.now_seconds);
}

MemoryEngine::~MemoryEngine() = default;

absl::StatusOr<std::unique_ptr<MemoryEngine>> MemoryEngine::Open(
    EngineOptions options, MemoryStore* store, PlaceIndexFactory index_factory,
    EngineHooks hooks) {
  absl::Status status = ValidateEngineOptions(options);
  if (!status.ok()) return status;
  if (store == nullptr) {
    return absl::InvalidArgumentError("MemoryEngine::Open needs a store");
  }
  if (!index_factory) {
    return absl::InvalidArgumentError(
        "MemoryEngine::Open needs an index factory");
  }
  std::unique_ptr<MemoryEngine> engine(new MemoryEngine(
      std::move(options), store, std::move(index_factory), std::move(hooks)));
  absl::StatusOr<std::vector<std::string>> fleet_ids = store->ListFleets();
  if (!fleet_ids.ok()) return fleet_ids.status();
  absl::MutexLock fleets_lock(&engine->fleets_mu_);
  for (const std::string& fleet_id : *fleet_ids) {
    auto fleet = std::make_unique<Fleet>(fleet_id, engine.get());
    {
      absl::MutexLock writer(&fleet->writer_mu);
      absl::MutexLock lock(&fleet->mu);
      status = fleet->Reload();
    }
    if (!status.ok()) {
      return absl::Status(
          status.code(),
          absl::StrCat("loading fleet \"", fleet_id, "\": ", status.message()));
    }
    engine->fleets_[fleet_id] = std::move(fleet);
  }
  FLEETMEM_LOG(kInfo) << "memory engine opened with " << fleet_ids->size()
                      << " fleet(s)";
  return engine;
}

MemoryEngine::Fleet* MemoryEngine::Fleet::Find(const MemoryEngine& engine,
                                               std::string_view fleet_id) {
  absl::ReaderMutexLock lock(&engine.fleets_mu_);
  auto it = engine.fleets_.find(std::string(fleet_id));
  return it == engine.fleets_.end() ? nullptr : it->second.get();
}

absl::StatusOr<MemoryEngine::Fleet*> MemoryEngine::Fleet::FindOrAdd(
    MemoryEngine& engine, std::string_view fleet_id, bool admit) {
  absl::MutexLock lock(&engine.fleets_mu_);
  auto it = engine.fleets_.find(std::string(fleet_id));
  if (it != engine.fleets_.end()) return it->second.get();
  if (admit) {
    absl::Status admitted =
        engine.quota_->AdmitNewFleet(fleet_id, engine.fleets_.size());
    if (!admitted.ok()) return admitted;
  }
  auto& fleet = engine.fleets_[std::string(fleet_id)];
  fleet = std::make_unique<Fleet>(std::string(fleet_id), &engine);
  return fleet.get();
}

void MemoryEngine::Fleet::Notify(MemoryEngine& engine,
                                 std::string_view fleet_id,
                                 uint64_t last_event_id) {
  if (last_event_id == 0) return;
  absl::ReaderMutexLock lock(&engine.listeners_mu_);
  for (const auto& [handle, listener] : engine.listeners_) {
    if (listener.fleet_id == fleet_id) listener.callback(last_event_id);
  }
}

absl::StatusOr<UploadResult> MemoryEngine::Upload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  // A log entry's traces were checked whole where it was appended: its
  // apply checks their shape (ValidateUpload's check_values).
  const bool check_values = log_position == 0;
  if (fleet == nullptr) {
    // Validated before a fleet object exists, so a bad first upload leaves
    // nothing behind.
    status = ValidateUpload(fleet_id, traces, nullptr,
                            options_.max_traces_per_upload, check_values);
    if (!status.ok()) return status;
    if (traces.empty()) return UploadResult{};
    // A log entry's fleet was admitted before it was acknowledged
    // (engine/admission.h): its apply is refused by no limit.
    if (check_values) {
      status = quota_->AdmitDimension(fleet_id, traces[0].code.size());
      if (!status.ok()) return status;
    }
    absl::StatusOr<Fleet*> added =
        Fleet::FindOrAdd(*this, fleet_id, /*admit=*/check_values);
    if (!added.ok()) return added.status();
    fleet = *added;
  }
  // Outside the writer lock, so that robots' segments cluster in parallel.
  const std::optional<core::ConsolidationPlan> plan = fleet->PlanAhead(traces);
  UploadResult result;
  Notices notices;
  status = fleet->WriteUpload(traces, log_position, plan ? &*plan : nullptr,
                              &result, &notices);
  Fleet::Notify(*this, fleet_id, notices.last_event_id);
  if (notices.consolidations > 0 && hooks_.on_consolidate) {
    hooks_.on_consolidate(fleet_id, notices.consolidations,
                          notices.consolidated, notices.consolidation_seconds);
  }
  if (!status.ok()) return status;
  if (hooks_.on_upload) hooks_.on_upload(fleet_id, result);
  return result;
}

absl::StatusOr<ConsolidateResult> MemoryEngine::Consolidate(
    std::string_view fleet_id) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  const absl::Time start = absl::Now();
  Notices notices;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    {
      absl::MutexLock lock(&fleet->mu);
      status = fleet->EnsureLoaded();
      if (!status.ok()) return status;
      if (!fleet->exists()) return FleetNotFound(fleet_id);
      std::vector<std::string> robot_ids;
      for (const auto& [robot_id, traces] : fleet->pending.by_robot()) {
        if (!traces.empty()) robot_ids.push_back(robot_id);
      }
      for (const std::string& robot_id : robot_ids) {
        status = fleet->ConsolidateRobot(robot_id, &notices);
        if (!status.ok()) break;
      }
    }
    if (status.ok()) status = fleet->StoreStaged(&notices);
    absl::MutexLock lock(&fleet->mu);
    notices.consolidated.clusters = fleet->memory.clusters().size();
    notices.consolidated.traces = fleet->memory.trace_count();
    fleet->PublishHeld();
  }
  Fleet::Notify(*this, fleet_id, notices.last_event_id);
  if (!status.ok()) return status;
  if (hooks_.on_consolidate) {
    hooks_.on_consolidate(fleet_id, notices.consolidations,
                          notices.consolidated,
                          absl::ToDoubleSeconds(absl::Now() - start));
  }
  return notices.consolidated;
}

absl::Status MemoryEngine::CheckSampleReplay(
    std::string_view fleet_id, std::string_view robot_id, size_t count,
    std::string_view request_id, const core::ReadFilter* filter) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (status.ok()) status = core::ValidateId("robot_id", robot_id);
  if (status.ok() && !request_id.empty()) {
    status = core::ValidateId("request_id", request_id);
    if (status.ok() && request_id.size() > 64) {
      status =
          absl::InvalidArgumentError("request_id: longer than 64 characters");
    }
  }
  if (!status.ok()) return status;
  if (count < 1 || count > options_.max_sample_count) {
    return absl::InvalidArgumentError(absl::StrCat(
        "count is ", count, " but must be in 1..", options_.max_sample_count));
  }
  if (filter != nullptr) return core::ValidateReadFilter("filter", *filter);
  return absl::OkStatus();
}

absl::StatusOr<std::vector<core::MemoryTrace>> MemoryEngine::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, size_t count,
    std::string_view request_id, uint64_t log_position,
    const core::ReadFilter* filter) {
  absl::Status status =
      CheckSampleReplay(fleet_id, robot_id, count, request_id, filter);
  if (!status.ok()) return status;
  if (filter != nullptr && filter->selects_all()) filter = nullptr;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  absl::StatusOr<std::vector<core::MemoryTrace>> traces;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    FleetMutation mutation;
    {
      absl::MutexLock lock(&fleet->mu);
      status = fleet->EnsureLoaded();
      if (!status.ok()) return status;
      if (!fleet->exists()) return FleetNotFound(fleet_id);
      status = CheckReadSize(
          "count", count,
          4 * size_t{fleet->meta.code_dimension} + fleet->largest_attachment,
          options_.max_read_bytes);
      if (!status.ok()) return status;
      traces = fleet->DrawSample(robot_id, count, request_id, log_position,
                                 filter, &mutation);
    }
    if (traces.ok() && !mutation.put_robots.empty()) {
      // Readers may see the incremented counts while they are stored; if
      // the store fails, the fleet is reloaded and the call fails.
      {
        absl::ReaderMutexLock lock(&fleet->mu);
        status = store_->Apply(fleet->id, mutation);
      }
      absl::MutexLock lock(&fleet->mu);
      if (status.ok()) {
        fleet->FinishSample(std::move(mutation));
      } else {
        fleet->Reload().IgnoreError();
        traces = status;
      }
    }
  }
  if (traces.ok() && hooks_.on_sample) {
    hooks_.on_sample(fleet_id, traces->size());
  }
  return traces;
}

uint64_t MemoryEngine::Subscribe(std::string_view fleet_id,
                                 EventListener listener) {
  absl::MutexLock lock(&listeners_mu_);
  const uint64_t handle = next_listener_++;
  listeners_[handle] = Listener{std::string(fleet_id), std::move(listener)};
  return handle;
}

void MemoryEngine::Unsubscribe(uint64_t handle) {
  absl::MutexLock lock(&listeners_mu_);
  listeners_.erase(handle);
}

}  // namespace fleetmem::engine
