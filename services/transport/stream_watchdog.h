// Cancels a streaming call whose client does not move: armed when a read
// waits for the client's next message (an upload) or a write for the client
// to take it (a watch), disarmed when that completes. A stream that sends
// nothing, or a client that stopped reading, would otherwise hold its
// stream slot and memory until its deadline, if it has one.
#ifndef FLEETMEM_SERVICES_TRANSPORT_STREAM_WATCHDOG_H_
#define FLEETMEM_SERVICES_TRANSPORT_STREAM_WATCHDOG_H_

#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "grpcpp/alarm.h"
#include "grpcpp/server_context.h"

namespace fleetmem::transport {

// Not thread-safe: the reactor calls Arm and Disarm under its own lock. The
// alarm's callback touches only state it shares with the watchdog, so it
// may fire after the reactor is gone; Detach (in OnDone, before the context
// goes) makes it do nothing.
class StreamWatchdog {
 public:
  explicit StreamWatchdog(grpc::CallbackServerContext* context);
  ~StreamWatchdog();
  StreamWatchdog(const StreamWatchdog&) = delete;
  StreamWatchdog& operator=(const StreamWatchdog&) = delete;

  // Cancels the call (TryCancel) in `timeout` unless Disarm, Arm or Detach
  // comes first; `what` ends the warning logged then ("UploadTraces stream
  // of robot-7 cancelled: " + what).
  void Arm(absl::Duration timeout, std::string call, std::string what);
  void Disarm();
  // The context is about to go: a late alarm does nothing.
  void Detach();

 private:
  struct Shared {
    absl::Mutex mu;
    grpc::CallbackServerContext* context ABSL_GUARDED_BY(mu) = nullptr;
  };
  const std::shared_ptr<Shared> shared_;
  std::unique_ptr<grpc::Alarm> alarm_;
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_STREAM_WATCHDOG_H_
