#include "services/transport/stream_watchdog.h"

#include <chrono>
#include <utility>

#include "services/common/log.h"

namespace fleetmem::transport {

StreamWatchdog::StreamWatchdog(grpc::CallbackServerContext* context)
    : shared_(std::make_shared<Shared>()) {
  absl::MutexLock lock(&shared_->mu);
  shared_->context = context;
}

StreamWatchdog::~StreamWatchdog() {
  Detach();
  alarm_.reset();
}

void StreamWatchdog::Arm(absl::Duration timeout, std::string call,
                         std::string what) {
  alarm_ = std::make_unique<grpc::Alarm>();  // the one before is cancelled
  alarm_->Set(
      std::chrono::system_clock::now() + absl::ToChronoMilliseconds(timeout),
      [shared = shared_, call = std::move(call),
       what = std::move(what)](bool fired) {
        if (!fired) return;  // cancelled: the client moved
        absl::MutexLock lock(&shared->mu);
        if (shared->context == nullptr) return;  // the call is done
        FLEETMEM_LOG(kWarning) << call << " cancelled: " << what;
        shared->context->TryCancel();
      });
}

void StreamWatchdog::Disarm() { alarm_.reset(); }

void StreamWatchdog::Detach() {
  absl::MutexLock lock(&shared_->mu);
  shared_->context = nullptr;
}

}  // namespace fleetmem::transport
