#include "services/transport/service_state.h"

#include "services/transport/watch_reactor.h"

namespace fleetmem::transport {

bool ServiceState::AddWatch(WatchReactor* watch) {
  absl::MutexLock lock(&watches_mu_);
  if (shutting_down()) return false;
  watches_.insert(watch);
  return true;
}

void ServiceState::RemoveWatch(WatchReactor* watch) {
  absl::MutexLock lock(&watches_mu_);
  watches_.erase(watch);
}

void ServiceState::Shutdown() {
  // Under the lock, so that no watch registers after the flag is set and
  // none is deleted while it is being stopped (RemoveWatch waits).
  absl::MutexLock lock(&watches_mu_);
  shutting_down_.store(true, std::memory_order_release);
  for (WatchReactor* watch : watches_) watch->Stop();
}

}  // namespace fleetmem::transport
