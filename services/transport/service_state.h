// What the MemoryService's handlers and reactors share: the engine, the
// worker pool, the shutdown flag and the set of live watches.
#ifndef FLEETMEM_SERVICES_TRANSPORT_SERVICE_STATE_H_
#define FLEETMEM_SERVICES_TRANSPORT_SERVICE_STATE_H_

#include <atomic>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_set.h"
#include "absl/synchronization/mutex.h"
#include "services/auth/authenticator.h"
#include "services/engine/memory_engine.h"
#include "services/transport/work_queue.h"

namespace fleetmem::transport {

class WatchReactor;

// Thread-safe. Owned by the service; outlives every call (the server's
// Shutdown waits for all calls to end before the service is destroyed).
class ServiceState {
 public:
  // `engine`, `work` and `authenticator` must outlive this object; a null
  // `authenticator` means auth is off (every caller is an admin).
  ServiceState(engine::MemoryEngine* engine, WorkQueue* work,
               const auth::Authenticator* authenticator)
      : engine_(engine), work_(work), authenticator_(authenticator) {}

  engine::MemoryEngine& engine() const { return *engine_; }
  WorkQueue& work() const { return *work_; }
  const auth::Authenticator* authenticator() const { return authenticator_; }

  bool shutting_down() const {
    return shutting_down_.load(std::memory_order_acquire);
  }

  // Registers a live watch so that Shutdown can end it; false (nothing
  // registered) once Shutdown has begun.
  bool AddWatch(WatchReactor* watch);
  // Called by the watch when it is done, before it is deleted.
  void RemoveWatch(WatchReactor* watch);

  // New calls are refused from now on, and every live watch is finished.
  // Idempotent.
  void Shutdown();

 private:
  engine::MemoryEngine* const engine_;
  WorkQueue* const work_;
  const auth::Authenticator* const authenticator_;
  std::atomic<bool> shutting_down_{false};
  absl::Mutex watches_mu_;
  absl::flat_hash_set<WatchReactor*> watches_ ABSL_GUARDED_BY(watches_mu_);
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_SERVICE_STATE_H_
