// A fleet's whole state (engine::FleetImage) as bytes and back: distributed
// mode's snapshots (services/cluster) carry it from the replica that wrote
// it to one that restores it. The bytes are the fleet's records as the
// RocksDB store keys and encodes them (records.proto), so an image decodes
// with the same checks as a load: each record against its key, each
// cluster's members against its traces.
#ifndef FLEETMEM_SERVICES_STORAGE_FLEET_IMAGE_H_
#define FLEETMEM_SERVICES_STORAGE_FLEET_IMAGE_H_

#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "services/engine/memory_store.h"

namespace fleetmem::storage {

// INVALID_ARGUMENT for a malformed fleet id (the record's).
absl::StatusOr<std::string> EncodeFleetImage(const engine::FleetImage& image);

// DATA_LOSS naming the first record that does not parse, match its key or
// belong to `fleet_id`, or a trace no cluster lists.
absl::StatusOr<engine::FleetImage> DecodeFleetImage(std::string_view fleet_id,
                                                    std::string_view bytes);

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_FLEET_IMAGE_H_
