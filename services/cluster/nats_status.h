// nats.c's outcomes as absl::Status, and the hash that names a fleet's
// streams and keys. Internal to services/cluster.
#ifndef FLEETMEM_SERVICES_CLUSTER_NATS_STATUS_H_
#define FLEETMEM_SERVICES_CLUSTER_NATS_STATUS_H_

#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "nats/nats.h"

namespace fleetmem::cluster {

// True for the nats.c errors that say nothing of the request's outcome.
bool Unreachable(natsStatus status);

// 16 hex digits of the id's XXH3: ids hold characters that NATS subjects
// and keys do not allow (':').
std::string Hash(std::string_view fleet_id);

// A status for a failed nats.c call: UNAVAILABLE when NATS cannot be
// reached, DEADLINE_EXCEEDED on a timeout (the outcome is unknown), NOT_FOUND,
// else INTERNAL; the message has nats.c's own words and JetStream's code.
absl::Status FromNats(natsStatus status, int code, std::string_view what);

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_NATS_STATUS_H_
