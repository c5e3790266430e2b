// WatchMemory: a fleet's memory events after a cursor, then live ones.
#ifndef FLEETMEM_SERVICES_TRANSPORT_WATCH_REACTOR_H_
#define FLEETMEM_SERVICES_TRANSPORT_WATCH_REACTOR_H_

#include <cstdint>
#include <deque>
#include <memory>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "grpcpp/support/byte_buffer.h"
#include "grpcpp/support/server_callback.h"
#include "services/core/types.h"
#include "services/transport/service_state.h"
#include "services/transport/stream_watchdog.h"

namespace fleetmem::transport {

// Subscribes to the fleet's events first, then reads the stored events after
// the cursor in pages (MemoryEngine::ReadEvents, on the worker pool) and
// writes them one at a time (one write in flight). When it has caught up it
// waits for a notification from the engine, then reads again. Finishes OK
// when the call is cancelled or its deadline passes (OnCancel); UNAVAILABLE
// when the server shuts down (Stop), so that clients resume from their cursor
// elsewhere or later; INVALID_ARGUMENT for a bad fleet id;
// UNAUTHENTICATED / PERMISSION_DENIED from the access policy; the engine's
// error if a read fails; RESOURCE_EXHAUSTED if the pool is full. A watch
// whose client takes no event for ServiceOptions::stream_idle_timeout (its
// write stays in flight: the client stopped reading) is cancelled, so that
// it gives back its stream slot.
//
// Lifetime: created by the service, deleted in OnDone. The pool task and the
// engine listener do not point at the reactor directly but at a Shared block
// they co-own; OnDone clears Shared::reactor under Shared::mu, so a late task
// or notification finds nullptr instead of a deleted reactor.
class WatchReactor : public grpc::ServerWriteReactor<grpc::ByteBuffer> {
 public:
  // Authenticates and authorises the caller (auth::Action::kWatch) first.
  WatchReactor(ServiceState* state, grpc::CallbackServerContext* context,
               const v1::WatchMemoryRequest& request);

  // Finishes the call with UNAVAILABLE (server shutdown) once the write in
  // flight, if any, is done. Thread-safe.
  void Stop();
  // Finishes the call with `status` the same way (e.g. UNAVAILABLE when
  // this replica no longer owns the fleet). Thread-safe.
  void End(const grpc::Status& status);
  const std::string& fleet_id() const { return fleet_id_; }

  void OnWriteDone(bool ok) override;
  void OnCancel() override;
  void OnDone() override;

 private:
  struct Shared {
    absl::Mutex mu;
    WatchReactor* reactor ABSL_GUARDED_BY(mu) = nullptr;
  };

  // Each *Locked method requires shared_->mu.
  void ScheduleReadLocked();
  void OnEventsReadLocked(absl::StatusOr<std::vector<core::MemoryEvent>> read);
  void OnNotifyLocked(uint64_t last_event_id);
  void MaybeWriteLocked();
  void FinishLocked(grpc::Status status);

  ServiceState* const state_;
  std::string fleet_id_;  // resolved (an alias's fleet), set before use
  const std::shared_ptr<Shared> shared_;
  // Set in the constructor only (read in OnDone).
  bool registered_ = false;
  bool subscribed_ = false;
  uint64_t subscription_ = 0;
  std::string client_;  // holds a stream slot if set

  // Guarded by shared_->mu.
  uint64_t read_cursor_ = 0;  // id of the newest event read
  bool reading_ = false;      // a ReadEvents task is queued or running
  bool notified_ = false;     // events may exist beyond read_cursor_
  std::deque<core::MemoryEvent> unsent_;
  bool write_in_flight_ = false;
  grpc::ByteBuffer event_;  // the message being written (serialised)
  // Armed while a write waits for the client (stream_idle_timeout).
  StreamWatchdog stall_;
  bool finish_requested_ = false;
  grpc::Status final_status_;  // sent once no write is in flight
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_WATCH_REACTOR_H_
