#include "services/transport/watch_reactor.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/transport/call_auth.h"
#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"

namespace fleetmem::transport {

WatchReactor::WatchReactor(ServiceState* state,
                           grpc::CallbackServerContext* call,
                           const v1::WatchMemoryRequest& request)
    : state_(state),
      fleet_id_(request.fleet_id()),
      shared_(std::make_shared<Shared>()),
      read_cursor_(request.after_event()),
      stall_(call) {
  const grpc::CallbackServerContext& context = *call;
  // The checks of a watch over HTTP too (MemoryApi::CheckWatch): the fleet
  // id, the caller's rights, and the owner (a stream is not forwarded: the
  // client is sent to the replica that owns the fleet).
  absl::StatusOr<auth::Principal> caller =
      AuthenticateCall(state_->authenticator(), context);
  absl::Status valid = caller.status();
  if (valid.ok()) {
    absl::StatusOr<MemoryApi::Resolved> resolved =
        state_->api().CheckWatch(*caller, request);
    valid = resolved.status();
    if (valid.ok()) fleet_id_ = std::move(resolved->fleet_id);
  }
  std::string client;
  if (valid.ok()) {
    client = ClientName(state_->authenticator(), context, *caller);
    valid = state_->AcquireStream(client);
  }
  if (!valid.ok()) {
    absl::MutexLock lock(&shared_->mu);
    FinishLocked(ToGrpcStatus(valid));
    return;
  }
  client_ = std::move(client);
  if (!state_->AddWatch(this)) {
    absl::MutexLock lock(&shared_->mu);
    FinishLocked(ShuttingDownStatus());
    return;
  }
  registered_ = true;
  // Subscribe before the first read so that no event falls between them.
  // The listener only flags a wake-up; it never calls the engine.
  subscription_ = state_->engine().Subscribe(
      fleet_id_, [shared = shared_](uint64_t last_event_id) {
        absl::MutexLock lock(&shared->mu);
        if (shared->reactor != nullptr) {
          shared->reactor->OnNotifyLocked(last_event_id);
        }
      });
  subscribed_ = true;
  absl::MutexLock lock(&shared_->mu);
  shared_->reactor = this;
  ScheduleReadLocked();  // does nothing if Stop() came first
}

void WatchReactor::Stop() { End(ShuttingDownStatus()); }

void WatchReactor::End(const grpc::Status& status) {
  absl::MutexLock lock(&shared_->mu);
  FinishLocked(status);
}

void WatchReactor::ScheduleReadLocked() {
  if (finish_requested_ || reading_) return;
  reading_ = true;
  notified_ = false;
  bool queued =
      state_->work().TrySubmit([shared = shared_, engine = &state_->engine(),
                                fleet_id = fleet_id_, after = read_cursor_] {
        {
          absl::MutexLock lock(&shared->mu);
          if (shared->reactor == nullptr) return;
          if (shared->reactor->finish_requested_) {
            shared->reactor->reading_ = false;
            return;
          }
        }
        absl::StatusOr<std::vector<core::MemoryEvent>> read =
            engine->ReadEvents(fleet_id, after);
        absl::MutexLock lock(&shared->mu);
        if (shared->reactor != nullptr) {
          shared->reactor->OnEventsReadLocked(std::move(read));
        }
      });
  if (!queued) {
    reading_ = false;
    FinishLocked(ServerBusyStatus());
  }
}

void WatchReactor::OnEventsReadLocked(
    absl::StatusOr<std::vector<core::MemoryEvent>> read) {
  reading_ = false;
  if (finish_requested_) return;
  if (!read.ok()) {
    FLEETMEM_LOG(kWarning) << "WatchMemory " << fleet_id_ << ": "
                           << read.status();
    FinishLocked(ToGrpcStatus(read.status()));
    return;
  }
  if (!read->empty()) {
    read_cursor_ = read->back().id;
    // A full page may have more behind it: read again once these are sent.
    notified_ = true;
  }
  for (core::MemoryEvent& event : *read) unsent_.push_back(std::move(event));
  MaybeWriteLocked();
}

void WatchReactor::OnNotifyLocked(uint64_t last_event_id) {
  if (last_event_id <= read_cursor_) return;
  notified_ = true;
  MaybeWriteLocked();
}

void WatchReactor::MaybeWriteLocked() {
  if (finish_requested_ || write_in_flight_) return;
  if (unsent_.empty()) {
    if (notified_) ScheduleReadLocked();
    return;
  }
  v1::MemoryEvent event;
  EventToProto(unsent_.front(), &event);
  grpc::Slice slice(event.SerializeAsString());
  event_ = grpc::ByteBuffer(&slice, 1);
  unsent_.pop_front();
  write_in_flight_ = true;
  // The client has stream_idle_timeout to take it; a watch whose client
  // stopped reading holds a stream slot.
  stall_.Arm(
      state_->options().stream_idle_timeout,
      absl::StrCat("WatchMemory of fleet \"", fleet_id_, "\" by ", client_),
      "the client took no event for stream_idle_timeout");
  StartWrite(&event_);
}

void WatchReactor::OnWriteDone(bool ok) {
  absl::MutexLock lock(&shared_->mu);
  write_in_flight_ = false;
  stall_.Disarm();
  if (finish_requested_) {
    Finish(final_status_);  // deferred until the write was done
    return;
  }
  if (!ok) {
    FinishLocked(grpc::Status::OK);  // the stream is broken (cancelled)
    return;
  }
  MaybeWriteLocked();
}

void WatchReactor::OnCancel() {
  absl::MutexLock lock(&shared_->mu);
  FinishLocked(grpc::Status::OK);
}

void WatchReactor::FinishLocked(grpc::Status status) {
  if (finish_requested_) return;
  finish_requested_ = true;
  if (write_in_flight_) {
    final_status_ = std::move(status);  // OnWriteDone finishes
    return;
  }
  Finish(std::move(status));
}

void WatchReactor::OnDone() {
  if (registered_) state_->RemoveWatch(this);
  {
    absl::MutexLock lock(&shared_->mu);
    shared_->reactor = nullptr;
    stall_.Detach();  // the context goes with this reactor
    stall_.Disarm();
  }
  if (subscribed_) state_->engine().Unsubscribe(subscription_);
  if (!client_.empty()) state_->ReleaseStream(client_);
  delete this;
}

}  // namespace fleetmem::transport
