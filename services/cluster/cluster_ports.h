// Distributed mode's ports beside the fleet log (engine/fleet_log.h, the
// one log both modes write; docs/distributed.md): the snapshots from which
// a replica restores a fleet instead of applying its whole log, and the
// leases that give each fleet one owner at a time.
// services/cluster/nats_fleet_log.h implements all three on NATS JetStream.
#ifndef FLEETMEM_SERVICES_CLUSTER_CLUSTER_PORTS_H_
#define FLEETMEM_SERVICES_CLUSTER_CLUSTER_PORTS_H_

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fleetmem::cluster {

// A snapshot of a fleet's materialised state (storage's fleet image) and
// the last log entry it covers: a replica restores it and applies only the
// entries after `sequence`.
struct SnapshotInfo {
  uint64_t sequence = 0;
  uint64_t bytes = 0;  // of the image
  // The fleet's shape (its first upload's), for uploads checked by replicas
  // that do not hold the fleet once its first entry is trimmed.
  uint32_t code_dimension = 0;
  std::string encoder_version;
};

class SnapshotStore {
 public:
  virtual ~SnapshotStore() = default;
  // Stores `image` as the fleet's latest snapshot, and returns once it is
  // whole on the store's replicas; the earlier one is dropped then.
  // FAILED_PRECONDITION, with nothing replaced, if a snapshot covering as
  // much or more was stored meanwhile (by a replica that owned the fleet
  // before or after this one).
  virtual absl::Status Put(std::string_view fleet_id, const SnapshotInfo& info,
                           std::string_view image) = 0;
  // The latest snapshot's description; nullopt if the fleet has none.
  virtual absl::StatusOr<std::optional<SnapshotInfo>> Latest(
      std::string_view fleet_id) = 0;
  // The latest snapshot with its image; nullopt if the fleet has none.
  // DATA_LOSS if its image is incomplete or fails its checksum.
  virtual absl::StatusOr<std::optional<std::pair<SnapshotInfo, std::string>>>
  Fetch(std::string_view fleet_id) = 0;
};

// One replica's hold on a fleet. `revision` grows with every acquisition
// and renewal, across owners: the fencing token every materialisation step
// carries.
struct Lease {
  std::string fleet_id;
  std::string owner;
  uint64_t revision = 0;
};

class LeaseTable {
 public:
  virtual ~LeaseTable() = default;
  // Takes the fleet's lease for `owner` if no one holds it (a lease not
  // renewed within its time-to-live is free) or `owner` itself does (a
  // restarted replica; ids must be unique to replicas). FAILED_PRECONDITION
  // naming the holder otherwise.
  virtual absl::StatusOr<Lease> Acquire(std::string_view fleet_id,
                                        std::string_view owner) = 0;
  // Extends a held lease and returns it with its new revision.
  // FAILED_PRECONDITION if it was lost (expired, or taken since).
  virtual absl::StatusOr<Lease> Renew(const Lease& lease) = 0;
  // Gives a held lease up; FAILED_PRECONDITION if it was lost already.
  virtual absl::Status Release(const Lease& lease) = 0;
  // The fleet's current lease, if anyone holds it.
  virtual absl::StatusOr<std::optional<Lease>> Holder(
      std::string_view fleet_id) = 0;

  // Says that `replica` is alive and owns `fleets` fleets; an announcement
  // not repeated within the leases' time-to-live expires (ClusterNode's
  // balancing).
  virtual absl::Status Announce(std::string_view replica, uint64_t fleets) = 0;
  // The replicas whose announcement has not expired, with the number of
  // fleets each announced, sorted by replica.
  virtual absl::StatusOr<std::vector<std::pair<std::string, uint64_t>>>
  Replicas() = 0;
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_CLUSTER_PORTS_H_
