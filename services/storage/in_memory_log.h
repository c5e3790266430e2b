// An engine::FleetLog in process memory, for tests: the port's semantics
// (engine/fleet_log.h) without durability. Thread-safe (one mutex).
#ifndef FLEETMEM_SERVICES_STORAGE_IN_MEMORY_LOG_H_
#define FLEETMEM_SERVICES_STORAGE_IN_MEMORY_LOG_H_

#include <memory>

#include "services/engine/fleet_log.h"

namespace fleetmem::storage {

// A new, empty log. Never fails.
std::unique_ptr<engine::FleetLog> NewInMemoryLog();

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_IN_MEMORY_LOG_H_
