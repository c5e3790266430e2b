#include "services/observability/metrics.h"

#include <algorithm>
#include <cstdio>
#include <ctime>
#include <functional>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/common/sanitizers.h"
#include "services/engine/memory_engine.h"
#include "services/engine/testing/forwarding_store.h"
#include "services/index/exact_index.h"
#include "services/observability/process_stats.h"
#include "services/storage/in_memory_store.h"

namespace fleetmem::observability {
namespace {

using ::testing::HasSubstr;

TEST(MetricsTest, EngineTransportAndStoreAreObserved) {
  Metrics metrics;
  std::unique_ptr<engine::MemoryStore> store =
      metrics.TimedStore(storage::NewInMemoryStore());
  engine::EngineOptions options;
  options.segment_size = 4;
  options.memory.clusters_per_batch = 2;
  options.memory.max_clusters = 1;  // one segment of 8: 2 clusters, 1 forgotten
  auto engine = engine::MemoryEngine::Open(
      options, store.get(),
      [](size_t dimension) { return index::NewExactIndex(dimension); },
      metrics.EngineHooks());
  ASSERT_TRUE(engine.ok());
  metrics.SetScrapeSources({engine->get(), store.get(), [] { return 7; }});
  std::vector<core::MemoryTrace> traces;
  for (uint64_t seq = 1; seq <= 8; ++seq) {
    core::MemoryTrace trace;
    trace.robot_id = "r1";
    trace.seq = seq;
    trace.code = {static_cast<float>(seq), 1.0f};
    trace.reward = 1.0f;
    traces.push_back(trace);
  }
  ASSERT_TRUE((*engine)->Upload("alpha", traces).ok());
  // One upload that fills two robots' segments: two consolidations.
  std::vector<core::MemoryTrace> two_robots;
  for (uint64_t seq = 1; seq <= 8; ++seq) {
    core::MemoryTrace trace = traces[seq - 1];
    trace.robot_id = seq <= 4 ? "r2" : "r3";
    two_robots.push_back(trace);
  }
  ASSERT_EQ((*engine)->Upload("beta", two_robots)->consolidations, 2u);
  ASSERT_EQ((*engine)->GetStats("beta")->consolidations, 2u);
  metrics.ObserveCall("grpc", "GetStats", absl::StatusCode::kOk, 0.002);
  metrics.ObserveCall("http", "GetStats", absl::StatusCode::kNotFound, 0.001);
  metrics.ObserveUploadBytes("alpha", 1234);

  const std::string text = metrics.Render();
  EXPECT_THAT(text, HasSubstr("fleetmem_fleet_traces{fleet=\"alpha\"} "));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_uploaded_traces_total{fleet=\"alpha\"} 8"));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_consolidations_total{fleet=\"alpha\"} 1"));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_consolidations_total{fleet=\"beta\"} 2"));
  EXPECT_THAT(
      text, HasSubstr("fleetmem_clusters_forgotten_total{fleet=\"alpha\"} 1"));
  EXPECT_THAT(text, HasSubstr("fleetmem_fleet_clusters{fleet=\"alpha\"} 1"));
  EXPECT_THAT(text, HasSubstr("fleetmem_build_info{version=\""));
  for (const char* name :
       {"process_cpu_seconds_total ", "process_resident_memory_bytes ",
        "process_open_fds ", "process_max_fds ", "process_start_time_seconds ",
        "process_virtual_memory_bytes "}) {
    EXPECT_THAT(text, HasSubstr(std::string("\n") + name)) << name;
  }
  EXPECT_THAT(text, HasSubstr("fleetmem_rpc_requests_total{code=\"NOT_FOUND\","
                              "method=\"GetStats\",transport=\"http\"} 1"));
  EXPECT_THAT(text, HasSubstr("fleetmem_rpc_errors_total{method=\"GetStats\","
                              "transport=\"http\"} 1"));
  EXPECT_THAT(text, HasSubstr("fleetmem_rpc_duration_seconds_count{method="
                              "\"GetStats\",transport=\"grpc\"} 1"));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_uploaded_bytes_total{fleet=\"alpha\"} 1234"));
  EXPECT_THAT(text, HasSubstr("fleetmem_work_queue_depth 7"));
  // One write per upload message and per consolidated segment at least.
  EXPECT_THAT(text, HasSubstr("fleetmem_store_write_duration_seconds_count"));
  EXPECT_THAT(text, ::testing::Not(HasSubstr(
                        "fleetmem_store_write_duration_seconds_count 0")));
  EXPECT_THAT(text, HasSubstr("# TYPE fleetmem_consolidation_duration_seconds "
                              "histogram"));
  for (const char* kind : {"in_use", "free", "mmapped"}) {
    EXPECT_THAT(text, HasSubstr(absl::StrCat("\nfleetmem_heap_bytes{kind=\"",
                                             kind, "\"} ")))
        << kind;
  }
}

// A store's memory report becomes fleetmem_store_memory_bytes by kind,
// through the timing decorator.
TEST(MetricsTest, TheStoresMemoryByKind) {
  class ReportingStore : public engine::ForwardingStore {
   public:
    using ForwardingStore::ForwardingStore;
    std::vector<std::pair<std::string, uint64_t>> MemoryUsage() override {
      return {{"memtables", 1234}, {"block_cache", 5678}};
    }
  };
  Metrics metrics;
  std::unique_ptr<engine::MemoryStore> inner = storage::NewInMemoryStore();
  std::unique_ptr<engine::MemoryStore> store =
      metrics.TimedStore(std::make_unique<ReportingStore>(inner.get()));
  metrics.SetScrapeSources({nullptr, store.get()});
  const std::string text = metrics.Render();
  EXPECT_THAT(
      text, HasSubstr("fleetmem_store_memory_bytes{kind=\"memtables\"} 1234"));
  EXPECT_THAT(
      text,
      HasSubstr("fleetmem_store_memory_bytes{kind=\"block_cache\"} 5678"));
}

// The load that leaves out the codes an index snapshot holds goes through to
// the store: the decorator once fell back to a load of every code (1 GB read
// and dropped at each restart of 1,000,000 traces).
TEST(MetricsTest, TheTimedStorePassesALoadWithoutHeldCodesOn) {
  class WatchingStore : public engine::ForwardingStore {
   public:
    using ForwardingStore::ForwardingStore;
    absl::StatusOr<engine::FleetRecord> LoadFleetWithoutHeldCodes(
        std::string_view fleet_id,
        const std::function<bool(const core::TraceKey&)>& code_held_elsewhere)
        override {
      asked_with_function = code_held_elsewhere != nullptr;
      return ForwardingStore::LoadFleetWithoutHeldCodes(fleet_id,
                                                        code_held_elsewhere);
    }
    absl::StatusOr<engine::FleetRecord> LoadFleet(
        std::string_view fleet_id) override {
      ++plain_loads;
      return ForwardingStore::LoadFleet(fleet_id);
    }
    bool asked_with_function = false;
    int plain_loads = 0;
  };
  Metrics metrics;
  std::unique_ptr<engine::MemoryStore> inner = storage::NewInMemoryStore();
  auto watching = std::make_unique<WatchingStore>(inner.get());
  WatchingStore* watched = watching.get();
  std::unique_ptr<engine::MemoryStore> store =
      metrics.TimedStore(std::move(watching));
  ASSERT_TRUE(store
                  ->LoadFleetWithoutHeldCodes(
                      "f", [](const core::TraceKey&) { return true; })
                  .ok());
  EXPECT_TRUE(watched->asked_with_function);
  EXPECT_EQ(watched->plain_loads, 0);
}

// Distributed mode: a replica shows the gauges of the fleets it serves, and
// a fleet's go when it moves to another replica.
TEST(MetricsTest, AReplicaShowsOnlyTheFleetsItServes) {
  Metrics metrics;
  std::unique_ptr<engine::MemoryStore> store = storage::NewInMemoryStore();
  auto engine = engine::MemoryEngine::Open(
      {}, store.get(),
      [](size_t dimension) { return index::NewExactIndex(dimension); });
  ASSERT_TRUE(engine.ok());
  for (const std::string fleet : {"alpha", "beta"}) {
    core::MemoryTrace trace;
    trace.robot_id = "r1";
    trace.seq = 1;
    trace.code = {1.0f, 2.0f};
    ASSERT_TRUE((*engine)->Upload(fleet, {&trace, 1}).ok());
  }
  bool serves_beta = true;
  metrics.SetScrapeSources({engine->get(), store.get(), nullptr,
                            [&serves_beta](const std::string& fleet) {
                              return fleet == "alpha" || serves_beta;
                            }});
  std::string text = metrics.Render();
  EXPECT_THAT(text, HasSubstr("fleetmem_fleets 2"));
  EXPECT_THAT(text, HasSubstr("fleetmem_fleet_traces{fleet=\"beta\"}"));
  serves_beta = false;
  text = metrics.Render();
  EXPECT_THAT(text, HasSubstr("fleetmem_fleets 1"));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_fleet_pending_traces{fleet=\"alpha\"}"));
  EXPECT_THAT(text, ::testing::Not(HasSubstr("fleet=\"beta\"")));
}

TEST(MetricsTest, TheLogLagOfEachOwnedFleet) {
  Metrics metrics;
  std::vector<std::pair<std::string, double>> lag = {{"alpha", 3}, {"beta", 0}};
  ScrapeSources sources;
  sources.log_lag = [&lag] { return lag; };
  sources.cluster_fleets = [] { return std::pair<double, double>(5, 2); };
  metrics.SetScrapeSources(sources);
  std::string text = metrics.Render();
  EXPECT_THAT(text, HasSubstr("fleetmem_cluster_fleets 5"));
  EXPECT_THAT(text, HasSubstr("fleetmem_cluster_owned_fleets 2"));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_cluster_log_lag_entries{fleet=\"alpha\"} 3"));
  EXPECT_THAT(text,
              HasSubstr("fleetmem_cluster_log_lag_entries{fleet=\"beta\"} 0"));
  lag = {{"alpha", 0}};  // beta moved away
  text = metrics.Render();
  EXPECT_THAT(text,
              HasSubstr("fleetmem_cluster_log_lag_entries{fleet=\"alpha\"} 0"));
  EXPECT_THAT(text, ::testing::Not(HasSubstr("fleet=\"beta\"")));
}

// The timed store is what the server runs on: it must pass on every part of
// the port, index snapshots included.
TEST(MetricsTest, TimedStoreForwardsIndexSnapshots) {
  Metrics metrics;
  std::unique_ptr<engine::MemoryStore> store =
      metrics.TimedStore(storage::NewInMemoryStore());
  ASSERT_TRUE(store
                  ->SaveIndexSnapshot("f1",
                                      [](core::ByteWriter& out) {
                                        out.Put<uint32_t>(42);
                                        return absl::OkStatus();
                                      })
                  .ok());
  uint32_t read = 0;
  ASSERT_TRUE(store
                  ->ReadIndexSnapshot(
                      "f1",
                      [&read](const engine::IndexSnapshotBytes& snapshot) {
                        core::ByteReader in(snapshot.bytes);
                        in.Get(&read);
                        return absl::OkStatus();
                      })
                  .ok());
  EXPECT_EQ(read, 42u);
}

// Blocks allocated show in in_use (large ones in mmapped too) and leave it
// when freed.
TEST(ProcessStatsTest, HeapStatsFollowAllocations) {
  if (common::kSanitizerAllocator) GTEST_SKIP() << "the sanitizer's allocator";
  const HeapStats before = ReadHeapStats();
  std::vector<std::unique_ptr<char[]>> small;
  for (int i = 0; i < 1000; ++i) {
    small.emplace_back(new char[4096]);
    small.back()[0] = 1;
  }
  auto large = std::make_unique<char[]>(size_t{64} << 20);
  const HeapStats held = ReadHeapStats();
  EXPECT_GE(held.in_use_bytes - before.in_use_bytes, (64 << 20) + 1000 * 4096);
  EXPECT_GE(held.mmapped_bytes - before.mmapped_bytes, 64 << 20);
  small.clear();
  large.reset();
  const HeapStats after = ReadHeapStats();
  EXPECT_LE(after.in_use_bytes, held.in_use_bytes - (64 << 20));
}

// Freed blocks below one still held stay resident (malloc keeps them; only
// free memory at the top of a heap is returned by itself) until TrimHeap.
TEST(ProcessStatsTest, TrimHeapReturnsFreePages) {
  if (common::kSanitizerAllocator) GTEST_SKIP() << "the sanitizer's allocator";
  constexpr size_t kBlocks = 16384;  // 64 MiB of 4 KiB blocks
  std::vector<std::unique_ptr<char[]>> blocks;
  for (size_t i = 0; i < kBlocks; ++i) {
    blocks.emplace_back(new char[4096]);
    std::fill_n(blocks.back().get(), 4096, 1);  // resident
  }
  for (size_t i = 0; i + 1 < kBlocks; ++i) blocks[i].reset();  // last held
  absl::StatusOr<ProcessStats> before = ReadProcessStats();
  ASSERT_TRUE(before.ok());
  TrimHeap();
  absl::StatusOr<ProcessStats> after = ReadProcessStats();
  ASSERT_TRUE(after.ok());
  EXPECT_GE(before->resident_bytes - after->resident_bytes, 32 << 20)
      << "RSS " << before->resident_bytes << " -> " << after->resident_bytes;
}

TEST(ProcessStatsTest, ReadsThisProcess) {
  absl::StatusOr<ProcessStats> before = ReadProcessStats();
  ASSERT_TRUE(before.ok()) << before.status();
  EXPECT_GT(before->resident_bytes, 1 << 20);
  EXPECT_GE(before->virtual_bytes, before->resident_bytes);
  EXPECT_GE(before->open_fds, 3);
  EXPECT_GE(before->max_fds, before->open_fds);
  const double now = static_cast<double>(std::time(nullptr));
  EXPECT_LE(before->start_time_seconds, now + 1);
  EXPECT_GT(before->start_time_seconds, now - 3600);  // a test's process
  std::FILE* file = std::tmpfile();
  ASSERT_NE(file, nullptr);
  absl::StatusOr<ProcessStats> after = ReadProcessStats();
  std::fclose(file);
  ASSERT_TRUE(after.ok());
  EXPECT_EQ(after->open_fds, before->open_fds + 1);
  EXPECT_GE(after->cpu_seconds, before->cpu_seconds);
}

}  // namespace
}  // namespace fleetmem::observability
