// For tests: a MemoryStore and a FleetLog that forward every call to
// another, for test doubles to override the calls they watch or fail.
#ifndef FLEETMEM_SERVICES_ENGINE_TESTING_FORWARDING_STORE_H_
#define FLEETMEM_SERVICES_ENGINE_TESTING_FORWARDING_STORE_H_

#include <cstdint>
#include <functional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_store.h"

namespace fleetmem::engine {

class ForwardingStore : public MemoryStore {
 public:
  explicit ForwardingStore(MemoryStore* inner) : inner_(inner) {}
  absl::StatusOr<std::vector<std::string>> ListFleets() override {
    return inner_->ListFleets();
  }
  absl::StatusOr<FleetRecord> LoadFleet(std::string_view fleet_id) override {
    return inner_->LoadFleet(fleet_id);
  }
  absl::StatusOr<FleetRecord> LoadFleetWithoutHeldCodes(
      std::string_view fleet_id,
      const std::function<bool(const core::TraceKey&)>& code_held_elsewhere)
      override {
    return inner_->LoadFleetWithoutHeldCodes(fleet_id, code_held_elsewhere);
  }
  absl::StatusOr<FleetRecord> LoadFleetWithoutClusters(
      std::string_view fleet_id) override {
    return inner_->LoadFleetWithoutClusters(fleet_id);
  }
  absl::Status Apply(std::string_view fleet_id,
                     const FleetMutation& mutation) override {
    return inner_->Apply(fleet_id, mutation);
  }
  absl::StatusOr<std::vector<core::MemoryEvent>> ReadEvents(
      std::string_view fleet_id, uint64_t after_event, size_t limit) override {
    return inner_->ReadEvents(fleet_id, after_event, limit);
  }

 private:
  MemoryStore* inner_;
};

class ForwardingLog : public FleetLog {
 public:
  explicit ForwardingLog(FleetLog* inner) : inner_(inner) {}
  absl::StatusOr<std::vector<AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const LogAppend> entries,
      const AppendOptions& options) override {
    return inner_->Append(fleet_id, entries, options);
  }
  absl::StatusOr<std::vector<LogEntry>> Read(std::string_view fleet_id,
                                             uint64_t after,
                                             size_t max_entries) override {
    return inner_->Read(fleet_id, after, max_entries);
  }
  absl::Status Trim(std::string_view fleet_id, uint64_t through) override {
    return inner_->Trim(fleet_id, through);
  }
  absl::StatusOr<LogBounds> Bounds(std::string_view fleet_id) override {
    return inner_->Bounds(fleet_id);
  }
  absl::StatusOr<std::vector<std::string>> Fleets() override {
    return inner_->Fleets();
  }
  std::vector<LostLogEntries> Losses(std::string_view fleet_id) override {
    return inner_->Losses(fleet_id);
  }

 private:
  FleetLog* inner_;
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_TESTING_FORWARDING_STORE_H_
