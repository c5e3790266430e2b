#include "services/transport/service_state.h"

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "services/core/absl_view.h"
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

void ServiceState::ObserveCall(std::string_view method, absl::StatusCode code,
                               absl::Time started) const {
  if (!options_.on_call) return;
  options_.on_call("grpc", method, code,
                   absl::ToDoubleSeconds(absl::Now() - started));
}

void ServiceState::Shutdown() {
  // Under the lock, so that no watch registers after the flag is set and
  // none is deleted while it is being stopped (RemoveWatch waits).
  absl::MutexLock lock(&watches_mu_);
  shutting_down_.store(true, std::memory_order_release);
  for (WatchReactor* watch : watches_) watch->Stop();
}

void ServiceState::EndWatches(std::string_view fleet_id) {
  absl::MutexLock lock(&watches_mu_);
  for (WatchReactor* watch : watches_) {
    if (watch->fleet_id() == fleet_id) {
      watch->End(grpc::Status(
          grpc::StatusCode::UNAVAILABLE,
          absl::StrCat("fleet \"", V(fleet_id),
                       "\" moved to another replica: watch it again from "
                       "your last event id")));
    }
  }
}

absl::Status ServiceState::AcquireStream(const std::string& client) {
  absl::MutexLock lock(&streams_mu_);
  size_t& open = streams_[client];
  if (options_.max_streams_per_client > 0 &&
      open >= options_.max_streams_per_client) {
    if (open == 0) streams_.erase(client);
    return absl::ResourceExhaustedError(absl::StrCat(
        "limit max_streams_per_client (", options_.max_streams_per_client,
        ") reached by ", client, ": close a stream or retry later"));
  }
  ++open;
  return absl::OkStatus();
}

void ServiceState::ReleaseStream(const std::string& client) {
  absl::MutexLock lock(&streams_mu_);
  auto it = streams_.find(client);
  if (it == streams_.end()) return;
  if (--it->second == 0) streams_.erase(it);
}

void ServiceState::BeginWork() {
  absl::MutexLock lock(&work_mu_);
  ++work_in_flight_;
}

void ServiceState::EndWork() {
  absl::MutexLock lock(&work_mu_);
  --work_in_flight_;
}

bool ServiceState::WaitIdle(absl::Time deadline) {
  absl::MutexLock lock(&work_mu_);
  auto idle = [this]() ABSL_SHARED_LOCKS_REQUIRED(work_mu_) {
    return work_in_flight_ <= 0;
  };
  return work_mu_.AwaitWithDeadline(absl::Condition(&idle), deadline);
}

}  // namespace fleetmem::transport
