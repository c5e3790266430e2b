// fleetmem-server's distributed mode (docs/distributed.md), started from
// the server's configuration: reads the peer token and CA files and
// connects to NATS JetStream for cluster::ReplicatedMemory, the transport's
// FleetMemory in that mode.
#ifndef FLEETMEM_SERVICES_SERVER_CLUSTER_MODE_H_
#define FLEETMEM_SERVICES_SERVER_CLUSTER_MODE_H_

#include <memory>

#include "absl/status/statusor.h"
#include "services/cluster/replicated_memory.h"
#include "services/engine/memory_engine.h"
#include "services/server/server_config.h"

namespace fleetmem::server {

// Connects to NATS (UNAVAILABLE when no server answers within
// cluster.connect_timeout) and reads the peer token and CA files
// (NOT_FOUND / INVALID_ARGUMENT). `engine` must outlive the result and run
// without upload rate limits.
absl::StatusOr<std::unique_ptr<cluster::ReplicatedMemory>> StartClusterMode(
    const ServerConfig& config, engine::MemoryEngine* engine);

}  // namespace fleetmem::server

#endif  // FLEETMEM_SERVICES_SERVER_CLUSTER_MODE_H_
