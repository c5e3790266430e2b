#include "services/engine/admission.h"

#include "absl/strings/str_format.h"
#include "services/core/absl_view.h"

namespace fleetmem::engine {

absl::Status AdmitShape(UploadQuota& quota, std::string_view fleet_id,
                        std::span<const core::MemoryTrace> traces,
                        const FleetShape* shape, size_t max_traces_per_upload) {
  absl::Status status =
      CheckTraces(fleet_id, traces, shape, max_traces_per_upload);
  if (status.ok() && shape == nullptr && !traces.empty()) {
    status = quota.AdmitDimension(fleet_id, traces[0].code.size());
  }
  return status;
}

absl::Status AdmitLoad(UploadQuota& quota, std::string_view fleet_id,
                       const FleetLoad& load, uint64_t accepted,
                       uint64_t max_backlog_traces) {
  if (accepted == 0) return absl::OkStatus();
  if (absl::Status stored =
          quota.AdmitStored(fleet_id, load.held + load.backlog, accepted);
      !stored.ok()) {
    return stored;
  }
  if (max_backlog_traces > 0 && load.backlog + accepted > max_backlog_traces) {
    return absl::ResourceExhaustedError(absl::StrFormat(
        "fleet \"%s\": the apply backlog holds %d traces (oldest %.1f s), "
        "%d more would pass its bound of %d (write_path.max_backlog_traces);"
        " nothing of this upload was stored: retry with backoff",
        V(fleet_id), load.backlog, load.oldest_seconds, accepted,
        max_backlog_traces));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::engine
