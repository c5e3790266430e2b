// An engine::MemoryStore in process memory, for engine unit tests: the same
// semantics as OpenRocksDbStore (see services/storage/rocksdb_store.h for the
// rules of Apply and LoadFleet) without durability. Thread-safe (one mutex).
#ifndef FLEETMEM_SERVICES_STORAGE_IN_MEMORY_STORE_H_
#define FLEETMEM_SERVICES_STORAGE_IN_MEMORY_STORE_H_

#include <memory>

#include "services/engine/memory_store.h"

namespace fleetmem::storage {

// A new, empty store. Never fails on storage (only on invalid input).
std::unique_ptr<engine::MemoryStore> NewInMemoryStore();

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_IN_MEMORY_STORE_H_
