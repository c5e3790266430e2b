// DeleteFleet's disk at scale (issue "Fleets an operator can manage": a
// fleet of 1,000,000 traces deleted frees 90 % of its disk within 60 s):
// a RocksDB store (the server's, synced) holding a fleet of --held 256-d
// traces (bench_data.h; K_max and N_max large enough that nothing is
// forgotten), its index snapshot saved, and a small fleet beside it that
// stays. Prints the store directory's bytes before and after
// MemoryEngine::DeleteFleet and the seconds the delete took (its range
// deletes, compaction and snapshot removal: the data is gone from the disk
// when it returns), and checks that the kept fleet is whole. Meanwhile one
// thread queries the kept fleet (QueryPlace k = 10) without pause: its
// latencies during the delete against its peer, the same queries just
// before it (the goal: p99 < 5 ms during the delete).
//
//   build/bin/fleetmem_delete_fleet_bench --held 1000000 --dir /tmp/del
#include <algorithm>
#include <atomic>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "bench/bench_data.h"
#include "services/common/cli_program.h"
#include "services/common/files.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/storage/rocksdb_store.h"

namespace fleetmem::engine {
namespace {

constexpr size_t kRobots = 8;
constexpr size_t kSegment = 1000;

// Latencies (ms) of QueryPlace on `fleet` in a loop until `stop`.
std::vector<double> QueryUntil(MemoryEngine& engine, const std::string& fleet,
                               const std::atomic<bool>& stop) {
  bench::CodeSource queries(256, 99);
  std::vector<double> ms;
  while (!stop.load()) {
    PlaceQuery query;
    query.code = queries.NextTrace("q", ms.size() + 1).code;
    query.k = 10;
    const absl::Time start = absl::Now();
    if (!engine.QueryPlace(fleet, query).ok()) std::abort();
    ms.push_back(absl::ToDoubleMilliseconds(absl::Now() - start));
  }
  return ms;
}

double Percentile(std::vector<double> ms, double p) {
  if (ms.empty()) return 0;
  std::sort(ms.begin(), ms.end());
  return ms[std::min(ms.size() - 1, static_cast<size_t>(p * ms.size()))];
}

// `count` traces of kRobots robots into `fleet`, a segment at a time.
bool Fill(MemoryEngine& engine, const std::string& fleet, size_t count,
          uint64_t seed) {
  bench::CodeSource source(256, seed);
  std::vector<uint64_t> next_seq(kRobots, 1);
  for (size_t filled = 0; filled < count; filled += kSegment) {
    const size_t robot = (filled / kSegment) % kRobots;
    const std::string robot_id = "robot-" + std::to_string(robot);
    std::vector<core::MemoryTrace> segment;
    for (size_t i = 0; i < kSegment && filled + i < count; ++i) {
      segment.push_back(source.NextTrace(robot_id, next_seq[robot]++));
    }
    if (!engine.Upload(fleet, segment).ok()) return false;
  }
  return true;
}

int Run(size_t held, const std::string& dir) {
  files::RemoveTree(dir).IgnoreError();
  absl::StatusOr<std::unique_ptr<MemoryStore>> store =
      storage::OpenRocksDbStore({.path = dir});
  if (!store.ok()) {
    std::fprintf(stderr, "%s\n", store.status().ToString().c_str());
    return 1;
  }
  EngineOptions options;
  options.memory.max_clusters = static_cast<int>(held);
  options.memory.max_traces_per_cluster = static_cast<int>(kSegment);
  options.segment_size = kSegment;
  options.max_traces_per_upload = kSegment;
  options.limits.max_traces_per_fleet = held + 20 * kSegment;
  absl::StatusOr<std::unique_ptr<MemoryEngine>> engine = MemoryEngine::Open(
      options, store->get(),
      [](size_t dimension) { return index::NewExactIndex(dimension); });
  if (!engine.ok()) {
    std::fprintf(stderr, "%s\n", engine.status().ToString().c_str());
    return 1;
  }
  const absl::Time start = absl::Now();
  if (!Fill(**engine, "big", held, 7) || !Fill(**engine, "kept", 10'000, 8)) {
    std::fprintf(stderr, "upload failed\n");
    return 1;
  }
  if (!(*engine)->SaveIndexSnapshots().ok()) {
    std::fprintf(stderr, "index snapshot failed\n");
    return 1;
  }
  const FleetStats big = *(*engine)->GetStats("big");
  const FleetStats kept = *(*engine)->GetStats("kept");
  const uint64_t before = files::BytesUnder(dir);
  std::printf(
      "filled in %.1f s: big %llu traces, kept %llu; %llu bytes\n",
      absl::ToDoubleSeconds(absl::Now() - start),
      static_cast<unsigned long long>(big.traces + big.pending_traces),
      static_cast<unsigned long long>(kept.traces + kept.pending_traces),
      static_cast<unsigned long long>(before));
  // The peer: the kept fleet's queries for a second before the delete.
  std::atomic<bool> stop = false;
  std::vector<double> before_ms;
  std::thread peer([&] { before_ms = QueryUntil(**engine, "kept", stop); });
  absl::SleepFor(absl::Seconds(1));
  stop = true;
  peer.join();
  stop = false;
  std::vector<double> during_ms;
  std::thread querying([&] { during_ms = QueryUntil(**engine, "kept", stop); });
  const absl::Time deleting = absl::Now();
  absl::StatusOr<uint64_t> deleted = (*engine)->DeleteFleet("big");
  const double seconds = absl::ToDoubleSeconds(absl::Now() - deleting);
  stop = true;
  querying.join();
  if (!deleted.ok()) {
    std::fprintf(stderr, "%s\n", deleted.status().ToString().c_str());
    return 1;
  }
  const uint64_t after = files::BytesUnder(dir);
  const FleetStats still = *(*engine)->GetStats("kept");
  std::printf(
      "DeleteFleet of %llu traces: %.2f s; store %llu -> %llu bytes "
      "(%.1f %% freed); kept fleet %s\n",
      static_cast<unsigned long long>(*deleted), seconds,
      static_cast<unsigned long long>(before),
      static_cast<unsigned long long>(after),
      100.0 * (1.0 - static_cast<double>(after) / static_cast<double>(before)),
      still.traces + still.pending_traces == kept.traces + kept.pending_traces
          ? "whole"
          : "CHANGED");
  std::printf(
      "QueryPlace k=10 on the kept fleet: during the delete %zu queries, "
      "p50 %.2f ms, p99 %.2f ms; before it (peer) %zu queries, p50 %.2f ms, "
      "p99 %.2f ms\n",
      during_ms.size(), Percentile(during_ms, 0.5), Percentile(during_ms, 0.99),
      before_ms.size(), Percentile(before_ms, 0.5),
      Percentile(before_ms, 0.99));
  return 0;
}

}  // namespace
}  // namespace fleetmem::engine

int main(int argc, char** argv) {
  CLI::App app(
      "fleetmem_delete_fleet_bench: DeleteFleet's time and freed disk at "
      "scale.");
  fleetmem::common::SetUpProgram(app, "fleetmem_delete_fleet_bench");
  size_t held = 1'000'000;
  std::string dir = "/tmp/fleetmem-delete-fleet-bench";
  app.add_option("--held", held, "traces of the fleet deleted");
  app.add_option("--dir", dir, "store directory (removed first)");
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  return fleetmem::engine::Run(held, dir);
}
