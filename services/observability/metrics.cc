#include "services/observability/metrics.h"

#include <algorithm>
#include <functional>
#include <sstream>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "fleetmem_version.h"
#include "prometheus/counter.h"
#include "prometheus/family.h"
#include "prometheus/gauge.h"
#include "prometheus/histogram.h"
#include "prometheus/registry.h"
#include "prometheus/text_serializer.h"
#include "services/observability/process_stats.h"

namespace fleetmem::observability {
namespace {

using prometheus::BuildCounter;
using prometheus::BuildGauge;
using prometheus::BuildHistogram;
using prometheus::Counter;
using prometheus::Family;
using prometheus::Gauge;
using prometheus::Histogram;

// Seconds, from half a millisecond (a query on a small fleet) to 10 s (a
// large consolidation or a stalled disk).
const Histogram::BucketBoundaries& LatencyBuckets() {
  static const Histogram::BucketBoundaries* buckets =
      new Histogram::BucketBoundaries{0.0005, 0.001, 0.0025, 0.005, 0.01,
                                      0.025,  0.05,  0.1,    0.25,  0.5,
                                      1.0,    2.5,   5.0,    10.0};
  return *buckets;
}

std::string CodeName(absl::StatusCode code) {
  return absl::StatusCodeToString(code);
}

// Times every Apply of the wrapped store.
class TimedMemoryStore final : public engine::MemoryStore {
 public:
  TimedMemoryStore(std::unique_ptr<engine::MemoryStore> store,
                   Histogram* writes, Counter* write_errors)
      : store_(std::move(store)),
        writes_(writes),
        write_errors_(write_errors) {}

  absl::StatusOr<std::vector<std::string>> ListFleets() override {
    return store_->ListFleets();
  }
  absl::StatusOr<engine::FleetRecord> LoadFleet(
      std::string_view fleet_id) override {
    return store_->LoadFleet(fleet_id);
  }
  absl::StatusOr<engine::FleetRecord> LoadFleetWithoutHeldCodes(
      std::string_view fleet_id,
      const std::function<bool(const core::TraceKey&)>& code_held_elsewhere)
      override {
    return store_->LoadFleetWithoutHeldCodes(fleet_id, code_held_elsewhere);
  }
  absl::StatusOr<engine::FleetRecord> LoadFleetWithoutClusters(
      std::string_view fleet_id) override {
    return store_->LoadFleetWithoutClusters(fleet_id);
  }
  absl::Status Apply(std::string_view fleet_id,
                     const engine::FleetMutation& mutation) override {
    const absl::Time start = absl::Now();
    absl::Status status = store_->Apply(fleet_id, mutation);
    writes_->Observe(absl::ToDoubleSeconds(absl::Now() - start));
    if (!status.ok()) write_errors_->Increment();
    return status;
  }
  absl::StatusOr<std::vector<core::MemoryEvent>> ReadEvents(
      std::string_view fleet_id, uint64_t after_event, size_t limit) override {
    return store_->ReadEvents(fleet_id, after_event, limit);
  }
  absl::Status Checkpoint(const std::string& directory) override {
    return store_->Checkpoint(directory);
  }
  absl::Status SaveIndexSnapshot(
      std::string_view fleet_id,
      const std::function<absl::Status(core::ByteWriter&)>& write,
      const std::function<void()>& written) override {
    return store_->SaveIndexSnapshot(fleet_id, write, written);
  }
  absl::Status ReadIndexSnapshot(
      std::string_view fleet_id,
      const engine::IndexSnapshotRead& read) override {
    return store_->ReadIndexSnapshot(fleet_id, read);
  }
  bool IndexSnapshotCurrent(std::string_view fleet_id) override {
    return store_->IndexSnapshotCurrent(fleet_id);
  }
  absl::Status DeleteFleet(std::string_view fleet_id,
                           const engine::FleetMeta& kept) override {
    return store_->DeleteFleet(fleet_id, kept);
  }
  absl::StatusOr<std::vector<engine::FleetAlias>> LoadAliases() override {
    return store_->LoadAliases();
  }
  absl::Status PutAlias(std::string_view alias,
                        std::string_view fleet_id) override {
    return store_->PutAlias(alias, fleet_id);
  }
  uint64_t ApproximateDiskBytes() override {
    return store_->ApproximateDiskBytes();
  }
  std::vector<std::pair<std::string, uint64_t>> MemoryUsage() override {
    return store_->MemoryUsage();
  }

 private:
  const std::unique_ptr<engine::MemoryStore> store_;
  Histogram* const writes_;
  Counter* const write_errors_;
};

// Times every append of the wrapped log: acknowledged uploads are writes
// too.
class TimedFleetLog final : public engine::FleetLog {
 public:
  TimedFleetLog(engine::FleetLog* log, Histogram* writes, Counter* write_errors)
      : log_(log), writes_(writes), write_errors_(write_errors) {}

  absl::StatusOr<std::vector<engine::AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const engine::LogAppend> entries,
      const engine::AppendOptions& options) override {
    const absl::Time start = absl::Now();
    absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
        log_->Append(fleet_id, entries, options);
    writes_->Observe(absl::ToDoubleSeconds(absl::Now() - start));
    if (!appended.ok()) write_errors_->Increment();
    return appended;
  }
  absl::StatusOr<std::vector<engine::LogEntry>> Read(
      std::string_view fleet_id, uint64_t after, size_t max_entries) override {
    return log_->Read(fleet_id, after, max_entries);
  }
  absl::Status Trim(std::string_view fleet_id, uint64_t through) override {
    return log_->Trim(fleet_id, through);
  }
  absl::StatusOr<engine::LogBounds> Bounds(std::string_view fleet_id) override {
    return log_->Bounds(fleet_id);
  }
  absl::StatusOr<std::vector<std::string>> Fleets() override {
    return log_->Fleets();
  }
  std::vector<engine::LostLogEntries> Losses(
      std::string_view fleet_id) override {
    return log_->Losses(fleet_id);
  }

 private:
  engine::FleetLog* const log_;
  Histogram* const writes_;
  Counter* const write_errors_;
};

}  // namespace

struct Metrics::Families {
  explicit Families(prometheus::Registry& r)
      : calls(BuildCounter()
                  .Name("fleetmem_rpc_requests_total")
                  .Help("Finished calls by transport, method and status code")
                  .Register(r)),
        call_errors(BuildCounter()
                        .Name("fleetmem_rpc_errors_total")
                        .Help("Finished calls whose status was not OK")
                        .Register(r)),
        call_seconds(BuildHistogram()
                         .Name("fleetmem_rpc_duration_seconds")
                         .Help("Call latency by transport and method, from "
                               "arrival to answer")
                         .Register(r)),
        uploaded_traces(BuildCounter()
                            .Name("fleetmem_uploaded_traces_total")
                            .Help("Traces stored by uploads (duplicates not "
                                  "counted)")
                            .Register(r)),
        duplicate_traces(BuildCounter()
                             .Name("fleetmem_duplicate_traces_total")
                             .Help("Uploaded traces the fleet already had")
                             .Register(r)),
        uploaded_bytes(BuildCounter()
                           .Name("fleetmem_uploaded_bytes_total")
                           .Help("Bytes of upload messages stored")
                           .Register(r)),
        consolidations(BuildCounter()
                           .Name("fleetmem_consolidations_total")
                           .Help("Robot segments consolidated (Algorithm 1)")
                           .Register(r)),
        clusters_added(BuildCounter()
                           .Name("fleetmem_clusters_added_total")
                           .Help("Clusters added by consolidation")
                           .Register(r)),
        clusters_forgotten(BuildCounter()
                               .Name("fleetmem_clusters_forgotten_total")
                               .Help("Clusters removed by forgetting "
                                     "(Algorithm 2)")
                               .Register(r)),
        forgetting_runs(BuildCounter()
                            .Name("fleetmem_forgetting_runs_total")
                            .Help("Consolidation calls in which forgetting "
                                  "removed at least one cluster")
                            .Register(r)),
        downsampled_traces(BuildCounter()
                               .Name("fleetmem_downsampled_traces_total")
                               .Help("Traces dropped by downsampling (Eq. 15)")
                               .Register(r)),
        consolidation_seconds(
            BuildHistogram()
                .Name("fleetmem_consolidation_duration_seconds")
                .Help("Time of one consolidation call, forgetting and the "
                      "durable write included")
                .Register(r)),
        sampled_traces(BuildCounter()
                           .Name("fleetmem_sampled_traces_total")
                           .Help("Traces handed out by SampleReplay (Eq. 18)")
                           .Register(r)),
        retention_deleted_traces(
            BuildCounter()
                .Name("fleetmem_retention_deleted_traces_total")
                .Help("Traces deleted by a fleet's retention (max age, max "
                      "traces per robot)")
                .Register(r)),
        query_seconds(BuildHistogram()
                          .Name("fleetmem_query_duration_seconds")
                          .Help("QueryPlace search time in the engine")
                          .Register(r)),
        index_snapshot_seconds(
            BuildHistogram()
                .Name("fleetmem_index_snapshot_pause_seconds")
                .Help("Time one fleet's uploads waited while its index "
                      "snapshot was written (periodic or at shutdown; the "
                      "file's sync follows without the wait)")
                .Register(r)),
        store_write_seconds(BuildHistogram()
                                .Name("fleetmem_store_write_duration_seconds")
                                .Help("Durable write (RocksDB WriteBatch with "
                                      "fsync) time")
                                .Register(r)),
        store_write_errors(BuildCounter()
                               .Name("fleetmem_store_write_errors_total")
                               .Help("Durable writes that failed")
                               .Register(r)),
        build_info(BuildGauge()
                       .Name("fleetmem_build_info")
                       .Help("1, labelled with the server's version")
                       .Register(r)),
        process_cpu(BuildCounter()
                        .Name("process_cpu_seconds_total")
                        .Help("User and system CPU time of the process")
                        .Register(r)),
        process_resident(BuildGauge()
                             .Name("process_resident_memory_bytes")
                             .Help("Resident memory of the process")
                             .Register(r)),
        process_virtual(BuildGauge()
                            .Name("process_virtual_memory_bytes")
                            .Help("Virtual memory of the process")
                            .Register(r)),
        process_open_fds(BuildGauge()
                             .Name("process_open_fds")
                             .Help("Open file descriptors")
                             .Register(r)),
        process_max_fds(BuildGauge()
                            .Name("process_max_fds")
                            .Help("The limit of open file descriptors")
                            .Register(r)),
        process_start(BuildGauge()
                          .Name("process_start_time_seconds")
                          .Help("Start time of the process, since the Unix "
                                "epoch")
                          .Register(r)),
        fleet_traces(BuildGauge()
                         .Name("fleetmem_fleet_traces")
                         .Help("Traces in the fleet's static memory")
                         .Register(r)),
        fleet_pending(BuildGauge()
                          .Name("fleetmem_fleet_pending_traces")
                          .Help("Traces awaiting consolidation")
                          .Register(r)),
        fleet_clusters(BuildGauge()
                           .Name("fleetmem_fleet_clusters")
                           .Help("Clusters in the fleet's static memory")
                           .Register(r)),
        fleet_robots(BuildGauge()
                         .Name("fleetmem_fleet_robots")
                         .Help("Robots that have uploaded to the fleet")
                         .Register(r)),
        fleet_last_event(BuildGauge()
                             .Name("fleetmem_fleet_last_event_id")
                             .Help("Id of the fleet's newest memory event")
                             .Register(r)),
        index_entries(BuildGauge()
                          .Name("fleetmem_index_entries")
                          .Help("Codes in the fleet's place index (static "
                                "and pending traces)")
                          .Register(r)),
        index_unindexed(BuildGauge()
                            .Name("fleetmem_index_unindexed_codes")
                            .Help("Codes waiting outside the fleet's HNSW "
                                  "graph (scanned exactly until indexed)")
                            .Register(r)),
        backlog_entries(BuildGauge()
                            .Name("fleetmem_write_backlog_entries")
                            .Help("Uploads acknowledged (durable in the "
                                  "fleet's log) and not applied yet")
                            .Register(r)),
        backlog_traces(BuildGauge()
                           .Name("fleetmem_write_backlog_traces")
                           .Help("Traces of the fleet's acknowledged uploads "
                                 "not applied yet (bounded: "
                                 "write_path.max_backlog_traces)")
                           .Register(r)),
        backlog_age(BuildGauge()
                        .Name("fleetmem_write_backlog_age_seconds")
                        .Help("Age of the fleet's oldest acknowledged upload "
                              "not applied yet (0 with none)")
                        .Register(r)),
        apply_blocked(BuildGauge()
                          .Name("fleetmem_write_apply_blocked")
                          .Help("1 while the fleet's acknowledged uploads "
                                "wait to be applied because the store "
                                "refuses the apply (e.g. the disk below its "
                                "reserve): reads do not see them")
                          .Register(r)),
        log_entries_lost(BuildGauge()
                             .Name("fleetmem_log_entries_lost")
                             .Help("Acknowledged entries of the fleet's "
                                   "ingest log found damaged since the "
                                   "server started (DATA_LOSS: never "
                                   "applied; GetStats names them)")
                             .Register(r)),
        log_lag(BuildGauge()
                    .Name("fleetmem_cluster_log_lag_entries")
                    .Help("Distributed mode: entries of the fleet's log not "
                          "applied yet by this replica, its owner")
                    .Register(r)),
        cluster_fleets(BuildGauge()
                           .Name("fleetmem_cluster_fleets")
                           .Help("Distributed mode: fleets that have a log, "
                                 "as this replica last listed them")
                           .Register(r)),
        cluster_owned(BuildGauge()
                          .Name("fleetmem_cluster_owned_fleets")
                          .Help("Distributed mode: fleets this replica owns "
                                "(holds the lease of)")
                          .Register(r)),
        fleets(BuildGauge()
                   .Name("fleetmem_fleets")
                   .Help("Fleets held by the server")
                   .Register(r)),
        store_bytes(BuildGauge()
                        .Name("fleetmem_store_disk_bytes")
                        .Help("RocksDB live SST files plus memtables, bytes")
                        .Register(r)),
        store_memory(BuildGauge()
                         .Name("fleetmem_store_memory_bytes")
                         .Help("RocksDB's own memory by kind: memtables, "
                               "table_readers (index and filter blocks of "
                               "open table files), block_cache, "
                               "block_cache_pinned")
                         .Register(r)),
        heap(BuildGauge()
                 .Name("fleetmem_heap_bytes")
                 .Help("The C library's heap (glibc mallinfo2) by kind: "
                       "in_use (allocated), free (held by malloc, not "
                       "returned to the system), mmapped (large blocks, "
                       "part of in_use)")
                 .Register(r)),
        queue_depth(BuildGauge()
                        .Name("fleetmem_work_queue_depth")
                        .Help("Calls waiting for a worker thread")
                        .Register(r)) {}

  Family<Counter>& calls;
  Family<Counter>& call_errors;
  Family<Histogram>& call_seconds;
  Family<Counter>& uploaded_traces;
  Family<Counter>& duplicate_traces;
  Family<Counter>& uploaded_bytes;
  Family<Counter>& consolidations;
  Family<Counter>& clusters_added;
  Family<Counter>& clusters_forgotten;
  Family<Counter>& forgetting_runs;
  Family<Counter>& downsampled_traces;
  Family<Histogram>& consolidation_seconds;
  Family<Counter>& sampled_traces;
  Family<Counter>& retention_deleted_traces;
  Family<Histogram>& query_seconds;
  Family<Histogram>& index_snapshot_seconds;
  Family<Histogram>& store_write_seconds;
  Family<Counter>& store_write_errors;
  Family<Gauge>& build_info;
  Family<Counter>& process_cpu;
  Family<Gauge>& process_resident;
  Family<Gauge>& process_virtual;
  Family<Gauge>& process_open_fds;
  Family<Gauge>& process_max_fds;
  Family<Gauge>& process_start;
  Family<Gauge>& store_memory;
  Family<Gauge>& heap;
  Family<Gauge>& fleet_traces;
  Family<Gauge>& fleet_pending;
  Family<Gauge>& fleet_clusters;
  Family<Gauge>& fleet_robots;
  Family<Gauge>& fleet_last_event;
  Family<Gauge>& index_entries;
  Family<Gauge>& index_unindexed;
  Family<Gauge>& backlog_entries;
  Family<Gauge>& backlog_traces;
  Family<Gauge>& backlog_age;
  Family<Gauge>& apply_blocked;
  Family<Gauge>& log_entries_lost;
  Family<Gauge>& log_lag;
  Family<Gauge>& cluster_fleets;
  Family<Gauge>& cluster_owned;
  Family<Gauge>& fleets;
  Family<Gauge>& store_bytes;
  Family<Gauge>& queue_depth;
};

Metrics::Metrics()
    : registry_(std::make_shared<prometheus::Registry>()),
      families_(std::make_unique<Families>(*registry_)) {
  // Zero-valued series exist from the start, so rate() has a baseline.
  families_->store_write_errors.Add({});
  families_->fleets.Add({});
  families_->store_bytes.Add({});
  families_->queue_depth.Add({});
  families_->build_info.Add({{"version", FLEETMEM_VERSION}}).Set(1);
}

Metrics::~Metrics() = default;

engine::EngineHooks Metrics::EngineHooks() {
  Families* f = families_.get();
  engine::EngineHooks hooks;
  hooks.on_upload = [f](std::string_view fleet,
                        const engine::UploadResult& result) {
    const prometheus::Labels labels{{"fleet", std::string(fleet)}};
    f->uploaded_traces.Add(labels).Increment(
        static_cast<double>(result.accepted));
    f->duplicate_traces.Add(labels).Increment(
        static_cast<double>(result.duplicates));
  };
  hooks.on_consolidate = [f](std::string_view fleet, size_t consolidations,
                             const engine::ConsolidateResult& result,
                             double seconds) {
    const prometheus::Labels labels{{"fleet", std::string(fleet)}};
    // As GetStats counts them: one per robot batch (an upload may fill
    // several robots' segments at once).
    f->consolidations.Add(labels).Increment(
        static_cast<double>(consolidations));
    f->clusters_added.Add(labels).Increment(
        static_cast<double>(result.clusters_added));
    f->clusters_forgotten.Add(labels).Increment(
        static_cast<double>(result.clusters_forgotten));
    if (result.clusters_forgotten > 0)
      f->forgetting_runs.Add(labels).Increment();
    f->downsampled_traces.Add(labels).Increment(
        static_cast<double>(result.downsampled_traces));
    f->consolidation_seconds.Add(labels, LatencyBuckets()).Observe(seconds);
  };
  hooks.on_sample = [f](std::string_view fleet, size_t count) {
    f->sampled_traces.Add({{"fleet", std::string(fleet)}})
        .Increment(static_cast<double>(count));
  };
  hooks.on_retention = [f](std::string_view fleet, uint64_t traces) {
    f->retention_deleted_traces.Add({{"fleet", std::string(fleet)}})
        .Increment(static_cast<double>(traces));
  };
  hooks.on_query = [f](std::string_view fleet, double seconds) {
    f->query_seconds.Add({{"fleet", std::string(fleet)}}, LatencyBuckets())
        .Observe(seconds);
  };
  hooks.on_index_snapshot = [f](std::string_view fleet, double seconds) {
    f->index_snapshot_seconds
        .Add({{"fleet", std::string(fleet)}},
             prometheus::Histogram::BucketBoundaries{0.01, 0.1, 0.5, 1, 2, 5,
                                                     10, 30, 60})
        .Observe(seconds);
  };
  return hooks;
}

void Metrics::ObserveCall(std::string_view transport, std::string_view method,
                          absl::StatusCode code, double seconds) {
  const std::string t(transport);
  const std::string m(method);
  families_->calls
      .Add({{"transport", t}, {"method", m}, {"code", CodeName(code)}})
      .Increment();
  if (code != absl::StatusCode::kOk) {
    families_->call_errors.Add({{"transport", t}, {"method", m}}).Increment();
  }
  families_->call_seconds
      .Add({{"transport", t}, {"method", m}}, LatencyBuckets())
      .Observe(seconds);
}

void Metrics::ObserveUploadBytes(std::string_view fleet, size_t bytes) {
  families_->uploaded_bytes.Add({{"fleet", std::string(fleet)}})
      .Increment(static_cast<double>(bytes));
}

std::unique_ptr<engine::MemoryStore> Metrics::TimedStore(
    std::unique_ptr<engine::MemoryStore> store) {
  return std::make_unique<TimedMemoryStore>(
      std::move(store),
      &families_->store_write_seconds.Add({}, LatencyBuckets()),
      &families_->store_write_errors.Add({}));
}

std::unique_ptr<engine::FleetLog> Metrics::TimedLog(engine::FleetLog* log) {
  return std::make_unique<TimedFleetLog>(
      log, &families_->store_write_seconds.Add({}, LatencyBuckets()),
      &families_->store_write_errors.Add({}));
}

void Metrics::SetScrapeSources(ScrapeSources sources) {
  absl::MutexLock lock(&sources_mu_);
  sources_ = std::move(sources);
}

void Metrics::RefreshFleetGauges() {
  if (sources_.engine == nullptr) return;
  Families& f = *families_;
  std::vector<std::string> fleet_ids = sources_.engine->ListFleets();
  if (sources_.serves_fleet) {
    std::erase_if(fleet_ids, [this](const std::string& fleet_id) {
      return !sources_.serves_fleet(fleet_id);
    });
  }
  // Gauges of fleets no longer served here go.
  for (const std::string& fleet_id : exported_) {
    if (std::find(fleet_ids.begin(), fleet_ids.end(), fleet_id) !=
        fleet_ids.end()) {
      continue;
    }
    const prometheus::Labels labels{{"fleet", fleet_id}};
    for (prometheus::Family<prometheus::Gauge>* family :
         {&f.fleet_traces, &f.fleet_pending, &f.fleet_clusters, &f.fleet_robots,
          &f.fleet_last_event, &f.index_entries, &f.index_unindexed}) {
      family->Remove(&family->Add(labels));
    }
  }
  exported_ = fleet_ids;
  f.fleets.Add({}).Set(static_cast<double>(fleet_ids.size()));
  for (const std::string& fleet_id : fleet_ids) {
    absl::StatusOr<engine::FleetStats> stats =
        sources_.engine->GetStats(fleet_id);
    if (!stats.ok()) continue;
    const prometheus::Labels labels{{"fleet", fleet_id}};
    f.fleet_traces.Add(labels).Set(static_cast<double>(stats->traces));
    f.fleet_pending.Add(labels).Set(static_cast<double>(stats->pending_traces));
    f.fleet_clusters.Add(labels).Set(static_cast<double>(stats->clusters));
    f.fleet_robots.Add(labels).Set(static_cast<double>(stats->robots.size()));
    f.fleet_last_event.Add(labels).Set(
        static_cast<double>(stats->last_event_id));
    f.index_entries.Add(labels).Set(
        static_cast<double>(stats->traces + stats->pending_traces));
    f.index_unindexed.Add(labels).Set(
        static_cast<double>(stats->unindexed_codes));
  }
}

void Metrics::RefreshLogGauges() {
  Families& f = *families_;
  if (sources_.log_lag) {
    std::vector<std::string> fleets;
    for (const auto& [fleet_id, lag] : sources_.log_lag()) {
      f.log_lag.Add({{"fleet", fleet_id}}).Set(lag);
      fleets.push_back(fleet_id);
    }
    for (const std::string& fleet_id : lag_exported_) {
      if (std::find(fleets.begin(), fleets.end(), fleet_id) == fleets.end()) {
        f.log_lag.Remove(&f.log_lag.Add({{"fleet", fleet_id}}));
      }
    }
    lag_exported_ = std::move(fleets);
  }
  if (sources_.backlogs) {
    // Fleets are never removed in embedded mode: no series goes away.
    for (const auto& [fleet_id, backlog] : sources_.backlogs()) {
      const prometheus::Labels labels{{"fleet", fleet_id}};
      f.backlog_entries.Add(labels).Set(static_cast<double>(backlog.entries));
      f.backlog_traces.Add(labels).Set(static_cast<double>(backlog.traces));
      f.backlog_age.Add(labels).Set(backlog.oldest_seconds);
      f.apply_blocked.Add(labels).Set(
          !backlog.apply_error.ok() && backlog.entries > 0 ? 1 : 0);
      f.log_entries_lost.Add(labels).Set(
          static_cast<double>(backlog.lost_entries()));
    }
  }
}

void Metrics::RefreshGauges() {
  absl::MutexLock lock(&sources_mu_);
  RefreshFleetGauges();
  RefreshLogGauges();
  Families& f = *families_;
  if (sources_.cluster_fleets) {
    const auto [with_log, owned] = sources_.cluster_fleets();
    f.cluster_fleets.Add({}).Set(with_log);
    f.cluster_owned.Add({}).Set(owned);
  }
  if (sources_.store != nullptr) {
    f.store_bytes.Add({}).Set(
        static_cast<double>(sources_.store->ApproximateDiskBytes()));
    for (const auto& [kind, bytes] : sources_.store->MemoryUsage()) {
      f.store_memory.Add({{"kind", kind}}).Set(static_cast<double>(bytes));
    }
  }
  if (sources_.work_queue_depth) {
    f.queue_depth.Add({}).Set(static_cast<double>(sources_.work_queue_depth()));
  }
  RefreshProcessGauges();
}

void Metrics::RefreshProcessGauges() {
  absl::StatusOr<ProcessStats> process = ReadProcessStats();
  if (!process.ok()) return;  // no /proc: the process_* series stay empty
  Families& f = *families_;
  prometheus::Counter& cpu = f.process_cpu.Add({});
  cpu.Increment(std::max(0.0, process->cpu_seconds - cpu.Value()));
  f.process_resident.Add({}).Set(process->resident_bytes);
  f.process_virtual.Add({}).Set(process->virtual_bytes);
  f.process_open_fds.Add({}).Set(process->open_fds);
  f.process_max_fds.Add({}).Set(process->max_fds);
  f.process_start.Add({}).Set(process->start_time_seconds);
  const HeapStats heap = ReadHeapStats();
  f.heap.Add({{"kind", "in_use"}}).Set(heap.in_use_bytes);
  f.heap.Add({{"kind", "free"}}).Set(heap.free_bytes);
  f.heap.Add({{"kind", "mmapped"}}).Set(heap.mmapped_bytes);
}

std::string Metrics::Render() {
  RefreshGauges();
  std::ostringstream out;
  prometheus::TextSerializer().Serialize(out, registry_->Collect());
  return out.str();
}

}  // namespace fleetmem::observability
