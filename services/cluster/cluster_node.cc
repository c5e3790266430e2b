#include "services/cluster/cluster_node.h"

#include <algorithm>
#include <utility>

#include "services/common/log.h"

namespace fleetmem::cluster {

ClusterNode::ClusterNode(ClusterNodeOptions options, engine::FleetLog* log,
                         LeaseTable* leases, SnapshotStore* snapshots,
                         engine::MemoryEngine* engine)
    : options_(std::move(options)),
      log_(log),
      leases_(leases),
      materialiser_(options_.materialiser, log, leases, snapshots, engine) {}

ClusterNode::~ClusterNode() { Stop(); }

void ClusterNode::Start() {
  if (thread_.joinable()) return;
  thread_ = std::thread([this] {
    while (!stop_.HasBeenNotified()) {
      absl::StatusOr<std::vector<std::string>> round = RunOnce();
      if (!round.ok()) {
        FLEETMEM_LOG(kWarning) << "cluster: " << round.status();
      }
      stop_.WaitForNotificationWithTimeout(options_.interval);
    }
  });
  if (options_.materialiser.renew_interval > absl::ZeroDuration()) {
    renewer_ = std::thread([this] {
      while (!stop_.WaitForNotificationWithTimeout(
          options_.materialiser.renew_interval / 2)) {
        materialiser_.RenewLeases();
      }
    });
  }
}

void ClusterNode::Stop() {
  if (!stop_.HasBeenNotified()) stop_.Notify();
  if (thread_.joinable()) thread_.join();
  if (renewer_.joinable()) renewer_.join();
}

void ClusterNode::ReleaseAll() {
  std::vector<std::string> fleets;
  {
    absl::MutexLock lock(&mu_);
    fleets = owned_;
    owned_.clear();
  }
  for (const std::string& fleet : fleets) {
    if (absl::Status released = materialiser_.Release(fleet); !released.ok()) {
      FLEETMEM_LOG(kWarning) << "cluster: " << released;
    }
  }
}

std::optional<uint64_t> ClusterNode::LeastLoadedOther(size_t owned) {
  // Announcements change once per renew_interval: read with this replica's
  // own, not every round.
  const absl::Time now = options_.materialiser.clock->Now();
  if (now - announced_at_ < options_.materialiser.renew_interval) {
    return least_other_;
  }
  const std::string& self = options_.materialiser.replica_id;
  if (absl::Status announced = leases_->Announce(self, owned);
      !announced.ok()) {
    FLEETMEM_LOG(kWarning) << "cluster: " << announced;
    return least_other_ = std::nullopt;  // asked again next round
  }
  announced_at_ = now;
  absl::StatusOr<std::vector<std::pair<std::string, uint64_t>>> replicas =
      leases_->Replicas();
  least_other_ = std::nullopt;
  if (!replicas.ok()) return least_other_;
  for (const auto& [replica, fleets] : *replicas) {
    if (replica == self) continue;
    least_other_ =
        least_other_.has_value() ? std::min(*least_other_, fleets) : fleets;
  }
  return least_other_;
}

absl::StatusOr<std::vector<std::string>> ClusterNode::RunOnce() {
  absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
  if (!fleets.ok()) return fleets.status();
  size_t mine = 0;
  for (const std::string& fleet : *fleets) {
    if (materialiser_.Owns(fleet)) ++mine;
  }
  const std::optional<uint64_t> least =
      options_.balance ? LeastLoadedOther(mine) : std::nullopt;
  std::vector<std::string> owned;
  for (const std::string& fleet : *fleets) {
    const bool held = materialiser_.Owns(fleet);
    // A free fleet is left to a less loaded replica.
    if (!held && least.has_value() && mine > *least) continue;
    absl::StatusOr<StepResult> step = materialiser_.Step(fleet);
    if (step.ok()) {
      owned.push_back(fleet);
      if (!held) ++mine;
    } else if (!absl::IsFailedPrecondition(step.status())) {
      // Still this replica's (unless its lease is gone); retried next round.
      if (materialiser_.lease(fleet).has_value()) owned.push_back(fleet);
      FLEETMEM_LOG(kWarning)
          << "cluster: fleet \"" << fleet << "\": " << step.status();
    }
  }
  if (least.has_value() && owned.size() > *least + 1) {
    // Hand one fleet over (the last by id): a less loaded replica takes it.
    const std::string fleet = owned.back();
    if (absl::Status released = materialiser_.Release(fleet); released.ok()) {
      FLEETMEM_LOG(kInfo) << "cluster: fleet \"" << fleet
                          << "\" handed over (this replica owned "
                          << owned.size() << ", another " << *least << ")";
      owned.pop_back();
    } else {
      FLEETMEM_LOG(kWarning) << "cluster: " << released;
    }
  }
  std::vector<std::string> before;
  {
    absl::MutexLock lock(&mu_);
    before = std::exchange(owned_, owned);
    fleets_seen_ = fleets->size();
  }
  if (on_lost_) {
    for (const std::string& fleet : before) {
      if (std::find(owned.begin(), owned.end(), fleet) == owned.end()) {
        on_lost_(fleet);
      }
    }
  }
  return owned;
}

std::vector<std::string> ClusterNode::owned() const {
  absl::MutexLock lock(&mu_);
  return owned_;
}

size_t ClusterNode::fleets_seen() const {
  absl::MutexLock lock(&mu_);
  return fleets_seen_;
}

}  // namespace fleetmem::cluster
