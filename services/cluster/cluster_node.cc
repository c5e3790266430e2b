#include "services/cluster/cluster_node.h"

#include <algorithm>
#include <utility>

#include "services/common/log.h"

namespace fleetmem::cluster {

ClusterNode::ClusterNode(ClusterNodeOptions options, FleetLog* log,
                         LeaseTable* leases, SnapshotStore* snapshots,
                         engine::MemoryEngine* engine)
    : options_(std::move(options)),
      log_(log),
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
}

void ClusterNode::Stop() {
  if (!stop_.HasBeenNotified()) stop_.Notify();
  if (thread_.joinable()) thread_.join();
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

absl::StatusOr<std::vector<std::string>> ClusterNode::RunOnce() {
  absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
  if (!fleets.ok()) return fleets.status();
  std::vector<std::string> owned;
  for (const std::string& fleet : *fleets) {
    absl::StatusOr<StepResult> step = materialiser_.Step(fleet);
    if (step.ok()) {
      owned.push_back(fleet);
    } else if (!absl::IsFailedPrecondition(step.status())) {
      // Still this replica's (unless its lease is gone); retried next round.
      if (materialiser_.lease(fleet).has_value()) owned.push_back(fleet);
      FLEETMEM_LOG(kWarning)
          << "cluster: fleet \"" << fleet << "\": " << step.status();
    }
  }
  std::vector<std::string> before;
  {
    absl::MutexLock lock(&mu_);
    before = std::exchange(owned_, owned);
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

}  // namespace fleetmem::cluster
