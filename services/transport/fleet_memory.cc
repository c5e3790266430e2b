#include "services/transport/fleet_memory.h"

#include "absl/strings/str_cat.h"
#include "services/common/log.h"

namespace fleetmem::transport {

std::vector<absl::StatusOr<Uploaded>> FleetMemory::UploadMany(
    std::string_view fleet_id,
    std::span<const std::span<const core::MemoryTrace>> messages,
    const UploadOptions& options) {
  std::vector<absl::StatusOr<Uploaded>> results;
  results.reserve(messages.size());
  for (size_t i = 0; i < messages.size(); ++i) {
    if (!results.empty() && !results.back().ok()) {
      results.push_back(absl::AbortedError(
          absl::StrCat("not stored: an upload before it in the same call was "
                       "refused")));
      continue;
    }
    results.push_back(Upload(fleet_id, messages[i], options));
  }
  return results;
}

uint64_t EnforceRetention(engine::MemoryEngine& engine, FleetMemory& memory,
                          int64_t now_ns) {
  absl::StatusOr<std::vector<std::pair<std::string, std::string>>> fleets =
      memory.Fleets();
  if (!fleets.ok()) {
    FLEETMEM_LOG(kWarning) << "retention: listing the fleets: "
                           << fleets.status();
    return 0;
  }
  uint64_t deleted = 0;
  for (const auto& [fleet_id, owner] : *fleets) {
    if (owner != memory.self()) continue;
    absl::StatusOr<engine::FleetInfo> info = engine.GetFleet(fleet_id);
    if (!info.ok() || (info->settings.max_age_seconds == 0 &&
                       info->settings.max_traces_per_robot == 0)) {
      continue;
    }
    absl::StatusOr<engine::AppliedRecord> applied =
        memory.Call(fleet_id, engine::EnforceRetentionRecord{now_ns});
    if (!applied.ok()) {
      FLEETMEM_LOG(kWarning)
          << "retention of fleet \"" << fleet_id << "\": " << applied.status();
      continue;
    }
    if (applied->deleted.deleted > 0) {
      FLEETMEM_LOG(kInfo) << "retention of fleet \"" << fleet_id
                          << "\": deleted " << applied->deleted.deleted
                          << " traces";
    }
    deleted += applied->deleted.deleted;
  }
  return deleted;
}

}  // namespace fleetmem::transport
