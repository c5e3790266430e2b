// Distributed mode's ports (docs/distributed.md): the replicated log that
// holds every fleet's writes in order, the source of truth from which
// replicas materialise a fleet's state, and the leases that give each fleet
// one owner at a time. services/cluster/nats_fleet_log.h implements both on
// NATS JetStream.
#ifndef FLEETMEM_SERVICES_CLUSTER_FLEET_LOG_H_
#define FLEETMEM_SERVICES_CLUSTER_FLEET_LOG_H_

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace fleetmem::cluster {

struct LogEntry {
  // From 1, growing; a replicated log may skip a number (JetStream does
  // when a proposal fails as its leader changes).
  uint64_t sequence = 0;
  std::string id;  // the id it was appended under
  std::string data;
};

struct Appended {
  uint64_t sequence = 0;
  // The log already held an entry under this id (within its deduplication
  // window): nothing was added; `sequence` is the earlier entry's.
  bool duplicate = false;
};

class FleetLog {
 public:
  virtual ~FleetLog() = default;
  // Appends `data` under `id` to the fleet's log (made on first use) and
  // returns once the log has stored it on its replicas. UNAVAILABLE or
  // DEADLINE_EXCEEDED: unknown whether it was stored; appending again
  // under the same id cannot store it twice within the window.
  virtual absl::StatusOr<Appended> Append(std::string_view fleet_id,
                                          std::string_view id,
                                          std::string_view data) = 0;
  // Up to `max` entries in order from sequence `from` (>= 1), skipping
  // numbers the log skipped; fewer at the end of the log (or after a failed
  // read), none past it or for a fleet without a log.
  virtual absl::StatusOr<std::vector<LogEntry>> Read(std::string_view fleet_id,
                                                     uint64_t from,
                                                     size_t max) = 0;
  // The fleet's last sequence; 0 for an empty log or none.
  virtual absl::StatusOr<uint64_t> LastSequence(std::string_view fleet_id) = 0;
  // The ids of the fleets that have a log, sorted.
  virtual absl::StatusOr<std::vector<std::string>> Fleets() = 0;
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
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_FLEET_LOG_H_
