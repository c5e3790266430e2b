// libFuzzer harness: bytes as a fleet image (distributed mode's snapshots
// arrive from NATS), through DecodeFleetImage's checks; an image that
// decodes encodes again and decodes to the same fleet.
#include <cstddef>
#include <cstdint>
#include <string>
#include <string_view>

#include "services/storage/fleet_image.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace storage = fleetmem::storage;
  const std::string_view bytes(reinterpret_cast<const char*>(data), size);
  absl::StatusOr<fleetmem::engine::FleetImage> image =
      storage::DecodeFleetImage("f1", bytes);
  if (!image.ok()) return 0;
  absl::StatusOr<std::string> again = storage::EncodeFleetImage(*image);
  if (!again.ok()) __builtin_trap();
  absl::StatusOr<fleetmem::engine::FleetImage> back =
      storage::DecodeFleetImage("f1", *again);
  if (!back.ok() ||
      back->record.pending.size() != image->record.pending.size() ||
      back->record.clusters.size() != image->record.clusters.size() ||
      back->events.size() != image->events.size()) {
    __builtin_trap();
  }
  return 0;
}
