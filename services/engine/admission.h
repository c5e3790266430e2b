// Admission: the checks an upload passes before it is acknowledged, the same
// in both modes. Embedded mode's WritePath admits in its group-commit leader;
// distributed mode's fleet owner (cluster::ReplicatedMemory, to which the
// other replicas forward uploads) admits with the same functions. Applying a
// log entry checks none of these limits again (MemoryEngine::Upload with a
// log position): an acknowledged upload is applied, even after a limit was
// lowered, so that a log is never stuck behind an entry it acknowledged.
//
// The rates (UploadQuota::AdmitRates) are the receiving replica's: not here.
#ifndef FLEETMEM_SERVICES_ENGINE_ADMISSION_H_
#define FLEETMEM_SERVICES_ENGINE_ADMISSION_H_

#include <cstddef>
#include <cstdint>
#include <optional>
#include <span>
#include <string_view>

#include "absl/status/status.h"
#include "services/core/types.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_engine.h"
#include "services/engine/upload_quota.h"

namespace fleetmem::engine {

// The shape a fleet's log entry gives it when it is the fleet's first: an
// upload's (its first trace's) or a CreateFleet's; none for another call.
inline std::optional<FleetShape> ShapeOfEntry(const LogEntry& entry) {
  if (const auto* create = std::get_if<CreateFleetRecord>(&entry.record)) {
    return FleetShape{create->code_dimension, create->encoder_version};
  }
  const std::span<const core::MemoryTrace> traces = entry.traces();
  if (traces.empty()) return std::nullopt;
  return FleetShape{static_cast<uint32_t>(traces[0].code.size()),
                    traces[0].encoder_version};
}

// The upload's traces are valid and of the fleet's shape (CheckTraces);
// for a new fleet (`shape` null), its code dimension within
// max_code_dimension. INVALID_ARGUMENT or RESOURCE_EXHAUSTED naming what.
absl::Status AdmitShape(UploadQuota& quota, std::string_view fleet_id,
                        std::span<const core::MemoryTrace> traces,
                        const FleetShape* shape, size_t max_traces_per_upload);

// What a fleet holds and has acknowledged, at an admission.
struct FleetLoad {
  uint64_t held = 0;          // traces applied (static memory + pending)
  uint64_t backlog = 0;       // traces acknowledged, not applied yet
  double oldest_seconds = 0;  // age of the oldest of those (for the message)
};

// `accepted` new traces (duplicates left out) fit in max_traces_per_fleet
// over held + backlog, and in `max_backlog_traces` over the backlog (0:
// unbounded). RESOURCE_EXHAUSTED naming the limit otherwise, counted as a
// refusal of the fleet (UploadQuota::Rejections).
absl::Status AdmitLoad(UploadQuota& quota, std::string_view fleet_id,
                       const FleetLoad& load, uint64_t accepted,
                       uint64_t max_backlog_traces);

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_ADMISSION_H_
