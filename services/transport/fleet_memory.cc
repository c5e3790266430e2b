#include "services/transport/fleet_memory.h"

#include "absl/strings/str_cat.h"

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

}  // namespace fleetmem::transport
