// Test helpers of the cluster module: a replica's engine on its own store,
// a fleet's uploads, and a fleet's memory as a comparable state.
#ifndef FLEETMEM_SERVICES_CLUSTER_TESTING_CLUSTER_TEST_UTIL_H_
#define FLEETMEM_SERVICES_CLUSTER_TESTING_CLUSTER_TEST_UTIL_H_

#include <memory>
#include <random>
#include <span>
#include <string>
#include <tuple>
#include <vector>

#include "gtest/gtest.h"
#include "services/cluster/materialiser.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_store.h"

namespace fleetmem::cluster::testing_util {

// Small memory, so that consolidation and forgetting run: segments of 20,
// at most 5 clusters of 3 traces.
inline engine::EngineOptions SmallOptions() {
  engine::EngineOptions options;
  options.memory.clusters_per_batch = 4;
  options.memory.max_traces_per_cluster = 3;
  options.memory.max_clusters = 5;
  options.segment_size = 20;
  options.max_traces_per_upload = 50;
  options.draw_in_memory_order = true;  // replicas draw alike
  return options;
}

// One replica's engine on its own store.
struct Replica {
  Replica() : store(storage::NewInMemoryStore()) {
    absl::StatusOr<std::unique_ptr<engine::MemoryEngine>> opened =
        engine::MemoryEngine::Open(
            SmallOptions(), store.get(),
            [](size_t dimension) { return index::NewExactIndex(dimension); });
    EXPECT_TRUE(opened.ok()) << opened.status();
    if (opened.ok()) engine = *std::move(opened);
  }
  std::unique_ptr<engine::MemoryStore> store;
  std::unique_ptr<engine::MemoryEngine> engine;
};

// Batches of 10 traces of 3 robots, interleaved; 8-d codes and places.
inline std::vector<std::vector<core::MemoryTrace>> Uploads() {
  std::mt19937_64 rng(11);
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  std::vector<std::vector<core::MemoryTrace>> uploads;
  for (uint64_t first = 1; first <= 60; first += 10) {
    for (const std::string robot : {"r1", "r2", "r3"}) {
      std::vector<core::MemoryTrace> batch;
      for (uint64_t seq = first; seq < first + 10; ++seq) {
        core::MemoryTrace trace;
        trace.robot_id = robot;
        trace.seq = seq;
        trace.domain = "summer";
        trace.encoder_version = "enc-v1";
        trace.code.resize(8);
        for (float& x : trace.code) x = gauss(rng);
        trace.place = {gauss(rng) * 30.0, gauss(rng) * 30.0, 0.0, 0.0};
        trace.reward = 0.5f + 0.1f * gauss(rng);
        trace.reward_external = trace.reward;
        batch.push_back(std::move(trace));
      }
      uploads.push_back(std::move(batch));
    }
  }
  return uploads;
}

// What a fleet's memory is: stats and every trace with its cluster.
struct State {
  engine::FleetStats stats;
  std::vector<std::tuple<std::string, uint64_t, uint64_t, uint32_t>> traces;
};
inline State StateOf(const engine::MemoryEngine& engine,
                     const std::string& fleet) {
  State state;
  absl::StatusOr<engine::FleetStats> stats = engine.GetStats(fleet);
  EXPECT_TRUE(stats.ok()) << stats.status();
  if (stats.ok()) state.stats = *stats;
  absl::StatusOr<engine::TracePage> page =
      engine.ListTraces(fleet, std::nullopt, 100000);
  EXPECT_TRUE(page.ok()) << page.status();
  if (!page.ok()) return state;
  for (const core::MemoryTrace& trace : page->traces) {
    state.traces.emplace_back(trace.robot_id, trace.seq, trace.cluster_id,
                              trace.replay_count);
  }
  return state;
}
inline void ExpectSameState(const State& a, const State& b) {
  EXPECT_EQ(a.stats.traces, b.stats.traces);
  EXPECT_EQ(a.stats.pending_traces, b.stats.pending_traces);
  EXPECT_EQ(a.stats.clusters, b.stats.clusters);
  EXPECT_EQ(a.stats.consolidations, b.stats.consolidations);
  EXPECT_EQ(a.stats.clusters_forgotten, b.stats.clusters_forgotten);
  ASSERT_EQ(a.stats.robots.size(), b.stats.robots.size());
  for (size_t i = 0; i < a.stats.robots.size(); ++i) {
    EXPECT_EQ(a.stats.robots[i].received, b.stats.robots[i].received);
    EXPECT_EQ(a.stats.robots[i].max_seq, b.stats.robots[i].max_seq);
  }
  EXPECT_EQ(a.traces, b.traces);
}

// Appends `traces` (one robot's) to the fleet's log as one upload entry,
// under their UploadId, or `id` where given.
inline absl::StatusOr<engine::AppendedEntry> AppendUpload(
    engine::FleetLog& log, const std::string& fleet,
    std::span<const core::MemoryTrace> traces, std::string id = "") {
  if (id.empty()) {
    absl::StatusOr<std::string> made = UploadId(traces);
    if (!made.ok()) return made.status();
    id = *std::move(made);
  }
  const engine::LogAppend append{engine::UploadRecord{traces}, id};
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log.Append(fleet, {&append, 1}, {});
  if (!appended.ok()) return appended.status();
  return appended->front();
}

// Appends every upload to the fleet's log.
inline void AppendUploads(
    engine::FleetLog& log, const std::string& fleet,
    const std::vector<std::vector<core::MemoryTrace>>& uploads) {
  for (const std::vector<core::MemoryTrace>& batch : uploads) {
    absl::StatusOr<engine::AppendedEntry> appended =
        AppendUpload(log, fleet, batch);
    ASSERT_TRUE(appended.ok()) << appended.status();
  }
}

}  // namespace fleetmem::cluster::testing_util

#endif  // FLEETMEM_SERVICES_CLUSTER_TESTING_CLUSTER_TEST_UTIL_H_
