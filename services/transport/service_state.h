// What the MemoryService's handlers and reactors share: the engine, the
// worker pool, the shutdown flag and the set of live watches.
#ifndef FLEETMEM_SERVICES_TRANSPORT_SERVICE_STATE_H_
#define FLEETMEM_SERVICES_TRANSPORT_SERVICE_STATE_H_

#include <atomic>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>
#include <string_view>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "services/auth/authenticator.h"
#include "services/engine/memory_engine.h"
#include "services/transport/memory_api.h"
#include "services/transport/work_queue.h"

namespace fleetmem::transport {

class WatchReactor;

// Observes every finished call, for metrics: the transport ("grpc",
// "http"), the method ("GetStats"), the status code and the seconds it took.
using CallObserver =
    std::function<void(std::string_view transport, std::string_view method,
                       absl::StatusCode code, double seconds)>;

struct ServiceOptions {
  // Options of the unary calls (snapshots, pages).
  ApiOptions api;
  // Called once per finished call (may be empty).
  CallObserver on_call;
  // Called with the size of each upload message stored (may be empty).
  std::function<void(std::string_view fleet_id, size_t bytes)> on_upload_bytes;

  // Upload and watch streams one client (ClientName) may hold open at once;
  // 0 = unlimited. One more is refused with RESOURCE_EXHAUSTED naming the
  // limit max_streams_per_client.
  size_t max_streams_per_client = 64;
  // An upload stream whose client sends neither a message nor the end of
  // the stream for this long is cancelled (its slot and memory come back);
  // so is a watch whose client takes no event for this long (it stopped
  // reading: the event's write stays in flight).
  absl::Duration stream_idle_timeout = absl::Seconds(60);
};

// Thread-safe. Owned by the service; outlives every call (the server's
// Shutdown waits for all calls to end before the service is destroyed).
class ServiceState {
 public:
  // `engine`, `memory`, `work` and `authenticator` must outlive this
  // object; a null `authenticator` means auth is off (every caller is an
  // admin).
  ServiceState(engine::MemoryEngine* engine, FleetMemory* memory,
               WorkQueue* work, const auth::Authenticator* authenticator,
               ServiceOptions options = {})
      : engine_(engine),
        memory_(memory),
        work_(work),
        authenticator_(authenticator),
        options_(options),
        api_(engine, memory, options.api) {}

  engine::MemoryEngine& engine() const { return *engine_; }
  // The mode: where uploads go, which server serves a fleet.
  FleetMemory& memory() const { return *memory_; }
  WorkQueue& work() const { return *work_; }
  const auth::Authenticator* authenticator() const { return authenticator_; }
  MemoryApi& api() { return api_; }
  const ServiceOptions& options() const { return options_; }

  // Reports a finished call to options().on_call, if set.
  void ObserveCall(std::string_view method, absl::StatusCode code,
                   absl::Time started) const;

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
  // Distributed mode: this replica no longer owns `fleet_id`; its watches
  // end with UNAVAILABLE, and their clients watch again (from their last
  // event id) through the fleet's new owner.
  void EndWatches(std::string_view fleet_id);

  // Work in flight: a unary call from submission to its answer, an upload
  // message from submission to its storage. Shutdown waits for these (up to
  // its grace), not for idle connections or streams waiting on a client.
  void BeginWork();
  void EndWork();
  // Blocks until no work is in flight or `deadline`; true if idle.
  bool WaitIdle(absl::Time deadline);

  // Takes one of `client`'s stream slots; RESOURCE_EXHAUSTED (limit
  // max_streams_per_client) when it holds them all. Each OK is matched by
  // one ReleaseStream.
  absl::Status AcquireStream(const std::string& client);
  void ReleaseStream(const std::string& client);

 private:
  engine::MemoryEngine* const engine_;
  FleetMemory* const memory_;
  WorkQueue* const work_;
  const auth::Authenticator* const authenticator_;
  const ServiceOptions options_;
  MemoryApi api_;
  mutable absl::Mutex streams_mu_;
  absl::flat_hash_map<std::string, size_t> streams_
      ABSL_GUARDED_BY(streams_mu_);
  absl::Mutex work_mu_;
  int64_t work_in_flight_ ABSL_GUARDED_BY(work_mu_) = 0;
  std::atomic<bool> shutting_down_{false};
  absl::Mutex watches_mu_;
  absl::flat_hash_set<WatchReactor*> watches_ ABSL_GUARDED_BY(watches_mu_);
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_SERVICE_STATE_H_
