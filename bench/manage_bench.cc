// Lookups by key at scale (issue "Fleets an operator can manage": GetTraces
// of 1,000 ids under 10 ms in process), each against its peer in the same
// run, in a fleet of 10,000 and 100,000 256-d traces (bench_data.h) held
// whole (K_max and N_max large enough that nothing is forgotten), the
// exact index holding the codes, the in-memory store:
//
//   build/bin/fleetmem_manage_bench --benchmark_min_time=0.5
//
// GetTraces/<held>: 1,000 random keys of the fleet, each trace with its
// code. Peer ListTracesPage/<held>: one page of 1,000 traces with their
// codes from a random cursor, the export's read (what a client without
// GetTraces pages through to find traces).
// FilteredQuery/<held>: QueryPlace k = 10 restricted to one robot of 10
// (10 % of the traces) on the HNSW index (the server's defaults), with
// recall@10 against the exact filtered answer (a scan of that robot's
// codes) as a counter. Peer Query/<held>: the same queries unfiltered.
#include <benchmark/benchmark.h>

#include <algorithm>
#include <cstdint>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench/bench_data.h"
#include "bench/bench_main.h"
#include "services/core/feature_space.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/index/hnsw_index.h"
#include "services/storage/in_memory_store.h"

namespace fleetmem::engine {
namespace {

constexpr size_t kRobots = 10;  // robot 3: a 10 % filter
constexpr size_t kSegment = 200;
constexpr size_t kAsked = 1000;

struct Fleet {
  std::unique_ptr<MemoryStore> store = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> engine;
  std::vector<core::TraceKey> keys;
  // Robot 3's traces' unit codes, by key (the exact filtered answer).
  std::vector<std::pair<core::TraceKey, std::vector<float>>> robot3;
  std::unique_ptr<bench::CodeSource> queries;
};

// A fleet of `held` traces (cached per size and index): kRobots robots'
// segments, on the exact index or (hnsw) the HNSW graph.
Fleet& Filled(size_t held, bool hnsw = false) {
  static std::map<std::pair<size_t, bool>, std::unique_ptr<Fleet>> cache;
  std::unique_ptr<Fleet>& slot = cache[{held, hnsw}];
  if (slot != nullptr) return *slot;
  slot = std::make_unique<Fleet>();
  EngineOptions options;
  options.memory.max_clusters = static_cast<int>(held);
  options.memory.max_traces_per_cluster = static_cast<int>(kSegment);
  options.segment_size = kSegment;
  options.max_keys_per_call = kAsked;
  slot->engine =
      *MemoryEngine::Open(options, slot->store.get(), [hnsw](size_t dimension) {
        return hnsw ? index::NewHnswIndex(dimension)
                    : index::NewExactIndex(dimension);
      });
  slot->queries = std::make_unique<bench::CodeSource>(256, 99);
  bench::CodeSource source(256, 7);
  std::vector<uint64_t> next_seq(kRobots, 1);
  for (size_t filled = 0; filled < held; filled += kSegment) {
    const size_t robot = (filled / kSegment) % kRobots;
    const std::string robot_id = "robot-" + std::to_string(robot);
    std::vector<core::MemoryTrace> segment;
    for (size_t i = 0; i < kSegment; ++i) {
      segment.push_back(source.NextTrace(robot_id, next_seq[robot]));
      slot->keys.push_back({robot_id, next_seq[robot]++});
      if (robot == 3) {
        slot->robot3.emplace_back(slot->keys.back(),
                                  core::NormalizedCode(segment.back().code));
      }
    }
    if (!slot->engine->Upload("f", segment).ok()) std::abort();
  }
  return *slot;
}

void BM_GetTraces(benchmark::State& state) {
  Fleet& fleet = Filled(static_cast<size_t>(state.range(0)));
  std::mt19937_64 rng(3);
  std::uniform_int_distribution<size_t> pick(0, fleet.keys.size() - 1);
  std::vector<core::TraceKey> asked(kAsked);
  for (auto _ : state) {
    state.PauseTiming();
    for (core::TraceKey& key : asked) key = fleet.keys[pick(rng)];
    state.ResumeTiming();
    absl::StatusOr<TraceLookup> found = fleet.engine->GetTraces("f", asked);
    if (!found.ok()) state.SkipWithError("GetTraces failed");
    benchmark::DoNotOptimize(found);
  }
  state.SetItemsProcessed(state.iterations() * kAsked);
}
BENCHMARK(BM_GetTraces)
    ->Arg(10'000)
    ->Arg(100'000)
    ->Unit(benchmark::kMillisecond);

void BM_ListTracesPage(benchmark::State& state) {
  Fleet& fleet = Filled(static_cast<size_t>(state.range(0)));
  std::mt19937_64 rng(3);
  std::uniform_int_distribution<size_t> pick(0, fleet.keys.size() - 1);
  for (auto _ : state) {
    const core::TraceKey after = fleet.keys[pick(rng)];
    absl::StatusOr<TracePage> page =
        fleet.engine->ListTraces("f", after, kAsked);
    if (!page.ok()) state.SkipWithError("ListTraces failed");
    benchmark::DoNotOptimize(page);
  }
  state.SetItemsProcessed(state.iterations() * kAsked);
}
BENCHMARK(BM_ListTracesPage)
    ->Arg(10'000)
    ->Arg(100'000)
    ->Unit(benchmark::kMillisecond);

// One query of k = 10 on the HNSW fleet, filtered to robot 3 or not;
// with the filter, recall@10 against the exact filtered answer.
void Query(benchmark::State& state, bool filtered) {
  Fleet& fleet = Filled(static_cast<size_t>(state.range(0)), /*hnsw=*/true);
  PlaceQuery query;
  query.k = 10;
  if (filtered) query.filter.robot_ids = {"robot-3"};
  double found = 0, wanted = 0;
  for (auto _ : state) {
    state.PauseTiming();
    query.code = fleet.queries->NextTrace("q", 1).code;
    state.ResumeTiming();
    absl::StatusOr<std::vector<PlaceMatch>> matches =
        fleet.engine->QueryPlace("f", query);
    if (!matches.ok()) state.SkipWithError("QueryPlace failed");
    if (!filtered) continue;
    state.PauseTiming();
    const std::vector<float> unit = core::NormalizedCode(query.code);
    std::vector<std::pair<float, core::TraceKey>> exact;
    for (const auto& [key, code] : fleet.robot3) {
      exact.emplace_back(core::CodeDistance(unit, code), key);
    }
    std::partial_sort(exact.begin(), exact.begin() + 10, exact.end());
    for (size_t i = 0; i < 10; ++i) {
      for (const PlaceMatch& match : *matches) {
        if (match.trace.key() == exact[i].second) ++found;
      }
    }
    wanted += 10;
    state.ResumeTiming();
  }
  if (filtered) state.counters["recall@10"] = found / std::max(1.0, wanted);
}

void BM_FilteredQuery(benchmark::State& state) { Query(state, true); }
void BM_Query(benchmark::State& state) { Query(state, false); }
BENCHMARK(BM_FilteredQuery)
    ->Arg(100'000)
    ->Arg(1'000'000)
    ->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Query)->Arg(100'000)->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace fleetmem::engine

int main(int argc, char** argv) {
  return fleetmem::bench::Main(
      argc, argv, "fleetmem_manage_bench",
      "lookups by key at scale: GetTraces of 1,000 ids against a page of "
      "ListTraces, filtered against plain queries.");
}
