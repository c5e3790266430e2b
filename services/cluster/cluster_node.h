// One replica's ownership loop in distributed mode (docs/distributed.md):
// every `interval` it lists the fleets that have a log, steps the
// Materialiser for each (taking the leases that are free, renewing its own,
// applying what its fleets' logs hold), and leaves the fleets other
// replicas own. A replica that stops (Stop, a crash) keeps its leases until
// they expire; the others then take its fleets.
#ifndef FLEETMEM_SERVICES_CLUSTER_CLUSTER_NODE_H_
#define FLEETMEM_SERVICES_CLUSTER_CLUSTER_NODE_H_

#include <atomic>
#include <functional>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "absl/time/time.h"
#include "services/cluster/cluster_ports.h"
#include "services/cluster/materialiser.h"
#include "services/engine/memory_engine.h"

namespace fleetmem::cluster {

struct ClusterNodeOptions {
  MaterialiserOptions materialiser;
  // Between two rounds over the fleets.
  absl::Duration interval = absl::Milliseconds(200);
  // Spreads the fleets over the live replicas. Each replica announces
  // itself and how many fleets it owns (LeaseTable::Announce, every
  // materialiser.renew_interval); it takes a free fleet only while it owns
  // no more than every other live replica, and while it owns two more than
  // the least loaded it hands one fleet over per round (releases its
  // lease: the taker restores its snapshot). A replica that joins thus
  // gets its share within a few rounds, and a lost replica's fleets go to
  // the least loaded survivors. Off: a replica takes every free fleet.
  bool balance = true;
};

class ClusterNode {
 public:
  // `log`, `leases`, `snapshots` and `engine` must outlive it; `snapshots`
  // may be null (Materialiser).
  ClusterNode(ClusterNodeOptions options, engine::FleetLog* log,
              LeaseTable* leases, SnapshotStore* snapshots,
              engine::MemoryEngine* engine);
  // Stops the loop (the leases are kept until they expire).
  ~ClusterNode();

  // Called for each fleet this replica owned after one round and not after
  // the next (on the loop's thread), and as soon as a lease is found lost
  // (Materialiser::OnLeaseLost: on the renewing thread too, so that a round
  // held up by other fleets' calls to NATS does not keep the fleet's
  // watches open). May be called twice for one loss. Set before Start.
  void OnFleetLost(std::function<void(const std::string&)> lost) {
    on_lost_ = lost;
    materialiser_.OnLeaseLost(std::move(lost));
  }
  // Runs rounds on a thread of its own until Stop, and renews the leases
  // held on another.
  void Start();
  // Ends the loop after its round; the leases are not given up.
  void Stop();
  // Gives up every lease held (a clean shutdown: others take the fleets at
  // once). Call after Stop.
  void ReleaseAll();

  // One round: every fleet in the log stepped once (with balancing: the
  // free ones only while this replica is among the least loaded), then at
  // most one fleet handed over. Returns the fleets this replica owns after
  // it; the log's error if it cannot list them.
  absl::StatusOr<std::vector<std::string>> RunOnce();
  // The fleets owned after the last round.
  std::vector<std::string> owned() const;
  // The fleets that had a log in the last round.
  size_t fleets_seen() const;
  // The materialiser the loop steps (for the calls an owner derives).
  Materialiser& materialiser() { return materialiser_; }

 private:
  // With balancing: the fewest fleets another live replica announced
  // (nullopt: no other replica, or the announcements cannot be read now:
  // then this replica takes every free fleet, so that none waits).
  std::optional<uint64_t> LeastLoadedOther(size_t owned);

  const ClusterNodeOptions options_;
  engine::FleetLog* const log_;
  LeaseTable* const leases_;
  Materialiser materialiser_;
  // Loop thread only: the last announcement, and what LeastLoadedOther
  // read with it.
  absl::Time announced_at_ = absl::InfinitePast();
  std::optional<uint64_t> least_other_;
  mutable absl::Mutex mu_;
  std::vector<std::string> owned_ ABSL_GUARDED_BY(mu_);
  size_t fleets_seen_ ABSL_GUARDED_BY(mu_) = 0;
  std::function<void(const std::string&)> on_lost_;
  absl::Notification stop_;
  std::thread thread_;
  // Renews the leases held (Materialiser::RenewLeases) every half
  // renew_interval, whatever the steps are doing.
  std::thread renewer_;
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_CLUSTER_NODE_H_
