// Prometheus metrics of the server, in one module: it observes the engine
// (EngineHooks), the transports (call and upload observers) and the store
// (a timing decorator), and reads gauges (per-fleet counts, index size, disk
// bytes, worker-queue depth) when scraped. Neither the memory code nor the
// transports call prometheus-cpp; they only call the hooks handed to them.
//
// Every metric is documented in docs/operations.md.
#ifndef FLEETMEM_SERVICES_OBSERVABILITY_METRICS_H_
#define FLEETMEM_SERVICES_OBSERVABILITY_METRICS_H_

#include <cstddef>
#include <functional>
#include <memory>
#include <string>
#include <string_view>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_engine.h"
#include "services/engine/memory_store.h"
#include "services/engine/write_path.h"

namespace prometheus {
class Registry;
}  // namespace prometheus

namespace fleetmem::observability {

// What is read at scrape time; every member may be empty/null.
struct ScrapeSources {
  const engine::MemoryEngine* engine = nullptr;
  engine::MemoryStore* store = nullptr;
  std::function<size_t()> work_queue_depth;
  // Distributed mode: whether this replica serves (owns) a fleet. The
  // per-fleet gauges show only those, so that summing over replicas counts
  // each fleet once; a fleet's gauges go when it moves away. Null: every
  // fleet the engine holds.
  std::function<bool(const std::string& fleet_id)> serves_fleet;
  // Distributed mode: entries of each owned fleet's log not applied yet
  // (fleetmem_cluster_log_lag_entries).
  std::function<std::vector<std::pair<std::string, double>>()> log_lag;
  // Distributed mode: the fleets that have a log and those this replica
  // owns, as of its last round (fleetmem_cluster_fleets,
  // fleetmem_cluster_owned_fleets: alerts compare them over replicas).
  std::function<std::pair<double, double>()> cluster_fleets;
  // Embedded mode: each fleet's write backlog (engine::WritePath):
  // fleetmem_write_backlog_entries, _traces and _age_seconds.
  std::function<std::vector<std::pair<std::string, engine::Backlog>>()>
      backlogs;
};

// Thread-safe.
class Metrics {
 public:
  Metrics();
  ~Metrics();
  Metrics(const Metrics&) = delete;
  Metrics& operator=(const Metrics&) = delete;

  // Hooks for MemoryEngine::Open (uploads, consolidations, samples, query
  // latency). They must not outlive this object.
  engine::EngineHooks EngineHooks();

  // One finished call of `method` on `transport` ("grpc", "http").
  void ObserveCall(std::string_view transport, std::string_view method,
                   absl::StatusCode code, double seconds);
  // One upload message of `bytes` stored for `fleet`.
  void ObserveUploadBytes(std::string_view fleet, size_t bytes);

  // `store` with every Apply timed (fleetmem_store_write_duration_seconds).
  std::unique_ptr<engine::MemoryStore> TimedStore(
      std::unique_ptr<engine::MemoryStore> store);
  // `log` with every Append timed by the same metric (an acknowledged
  // upload's write); `log` must outlive the result.
  std::unique_ptr<engine::FleetLog> TimedLog(engine::FleetLog* log);

  // Set once the engine and the pool exist (before the first scrape that
  // should show them).
  void SetScrapeSources(ScrapeSources sources);

  // Everything in the Prometheus text exposition format (version 0.0.4),
  // with the gauges read from the scrape sources now.
  std::string Render();

 private:
  struct Families;
  void RefreshGauges();
  // process_* from /proc (ReadProcessStats). Requires sources_mu_.
  void RefreshProcessGauges() ABSL_EXCLUSIVE_LOCKS_REQUIRED(sources_mu_);
  // RefreshGauges' parts: the served fleets' gauges (those of fleets no
  // longer served go), and their logs' (lag, backlog, losses).
  void RefreshFleetGauges() ABSL_EXCLUSIVE_LOCKS_REQUIRED(sources_mu_);
  void RefreshLogGauges() ABSL_EXCLUSIVE_LOCKS_REQUIRED(sources_mu_);

  std::shared_ptr<prometheus::Registry> registry_;
  std::unique_ptr<Families> families_;
  absl::Mutex sources_mu_;
  ScrapeSources sources_ ABSL_GUARDED_BY(sources_mu_);
  // Fleets whose gauges the last scrape set.
  std::vector<std::string> exported_ ABSL_GUARDED_BY(sources_mu_);
  std::vector<std::string> lag_exported_ ABSL_GUARDED_BY(sources_mu_);
};

}  // namespace fleetmem::observability

#endif  // FLEETMEM_SERVICES_OBSERVABILITY_METRICS_H_
