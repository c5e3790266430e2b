// Distributed mode's seam in the transport (docs/distributed.md): where an
// upload goes, which replica serves a fleet's calls, and the writes its
// owner derives from calls. services/server/cluster_mode.h implements it over
// services/cluster; the embedded mode has none (ServiceOptions::distribution
// null) and runs everything on its own engine.
#ifndef FLEETMEM_SERVICES_TRANSPORT_DISTRIBUTION_H_
#define FLEETMEM_SERVICES_TRANSPORT_DISTRIBUTION_H_

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "google/protobuf/message.h"
#include "services/core/types.h"
#include "services/engine/memory_engine.h"

namespace fleetmem::transport {

// Thread-safe.
class Distribution {
 public:
  virtual ~Distribution() = default;

  // Validates an upload (as the engine would) and appends it to the fleet's
  // log; returns once the log holds it on its replicas. `accepted` counts
  // the traces appended, `duplicates` those of entries the log already held
  // (a retry within its deduplication window); consolidations happen at the
  // owner and are not counted here.
  virtual absl::StatusOr<engine::UploadResult> Upload(
      std::string_view fleet_id, std::span<const core::MemoryTrace> traces) = 0;

  // Where the fleet's calls are served: nullopt for this replica (it owns
  // the fleet, or the fleet has no log yet and so does not exist), else the
  // owner's address. UNAVAILABLE when no replica holds the fleet right now
  // (an owner was lost and its lease has not expired yet).
  virtual absl::StatusOr<std::optional<std::string>> Owner(
      std::string_view fleet_id) = 0;
  // The fleets that have a log, and the owner of each (empty: none now;
  // this replica's own address when it owns it).
  virtual absl::StatusOr<std::vector<std::pair<std::string, std::string>>>
  Fleets() = 0;
  // This replica's address (its replica id).
  virtual const std::string& self() const = 0;

  // Calls the unary `method` ("QueryPlace") of fleetmem.v1.MemoryService
  // on the replica at `address`, marked as forwarded (that replica serves
  // it or answers UNAVAILABLE; it never forwards it again).
  virtual absl::Status Forward(const std::string& address,
                               std::string_view method,
                               const google::protobuf::Message& request,
                               google::protobuf::Message* response) = 0;

  // The writes an owner derives, through the fleet's log
  // (cluster::Materialiser). FAILED_PRECONDITION when this replica does not
  // own the fleet.
  virtual absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id) = 0;
  virtual absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view request_id) = 0;
};

// The metadata key that marks a forwarded call.
inline constexpr char kForwardedHeader[] = "x-fleetmem-forwarded";

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_DISTRIBUTION_H_
