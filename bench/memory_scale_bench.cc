// Costs of the static memory that should not grow with it (issue: P4, P5,
// statistics), each against its peer measured in the same run, at 5,000
// (the paper's memory), 100,000 and 1,000,000 traces of 256-d codes
// (bench_data.h). A full memory holds max_clusters = traces / 10 clusters of
// 10 traces (a 200-trace segment makes K = 20 clusters).
//
//   build/bin/fleetmem_memory_scale_bench --benchmark_min_time=0.5
//       --benchmark_out=scale.json --benchmark_out_format=json
//
// Consolidate/<traces>/<exact>: Algorithm 1 + 2 on one 200-trace segment
// into the full memory (k-means, downsampling, 20 clusters in, 20 forgotten)
// with forgetting's closest pair kept through the HNSW graph over centroids
// (exact = 0) or by exact scans (exact = 1: the previous implementation, the
// peer; not run at 1,000,000, where filling it takes O(K^2) = hours).
// SampleReplay/<traces>: 1,000 traces by Eq. 18 from the sum tree; the peer
// SampleReplayScan/<traces> is the previous implementation (every weight
// recomputed, Efraimidis-Spirakis keys, partial sort).
// Stats/<traces>: per-robot and per-domain counts from the kept counts; the
// peer StatsScan walks every trace (as GetStats did).
// Restore/<traces>: the static memory's share of a restart.
// KMeansSegment: k-means alone (Eq. 14, K = 20, at most 50 iterations) on
// one 200-trace segment shaped as fleetmem-load uploads it (gaussian 256-d
// codes, places 2 m apart on a line): the share of P1's upload path that
// Algorithm 1 fixes. Counters: Lloyd iterations and microseconds per trace.
#include <benchmark/benchmark.h>

#include <cstdint>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "bench/bench_data.h"
#include "bench/bench_main.h"
#include "services/core/feature_space.h"
#include "services/core/importance_sampler.h"
#include "services/core/kmeans.h"
#include "services/core/memory_options.h"
#include "services/core/static_memory.h"

namespace fleetmem::core {
namespace {

constexpr size_t kSegment = 200;
constexpr size_t kTracesPerCluster = 10;

struct Filled {
  std::unique_ptr<StaticMemory> memory;
  bench::CodeSource source{256, 7};
  uint64_t next_cluster = 1;
  uint64_t next_seq = 1;
  std::mt19937_64 rng{11};
};

// A full memory of `traces` traces (cached per size and mode): clusters of
// 10 consecutive traces put back with Restore, as a restart loads them.
Filled& Memory(size_t traces, bool exact) {
  static std::map<std::pair<size_t, bool>, std::unique_ptr<Filled>> cache;
  std::unique_ptr<Filled>& slot = cache[{traces, exact}];
  if (slot != nullptr) return *slot;
  slot = std::make_unique<Filled>();
  MemoryOptions options;
  options.max_clusters = static_cast<int>(traces / kTracesPerCluster);
  options.forgetting_exact_below =
      exact ? std::numeric_limits<int>::max() : options.forgetting_exact_below;
  slot->memory = std::make_unique<StaticMemory>(options);
  for (size_t c = 0; c < traces / kTracesPerCluster; ++c) {
    Cluster cluster;
    cluster.id = slot->next_cluster++;
    cluster.robot_id = "robot-" + std::to_string(c % 8);
    for (size_t i = 0; i < kTracesPerCluster; ++i) {
      cluster.traces.push_back(
          slot->source.NextTrace(cluster.robot_id, slot->next_seq++));
      cluster.traces.back().cluster_id = cluster.id;
    }
    slot->memory->Restore(std::move(cluster));
  }
  return *slot;
}

void BM_Consolidate(benchmark::State& state) {
  const size_t traces = static_cast<size_t>(state.range(0));
  Filled& filled = Memory(traces, state.range(1) != 0);
  for (auto _ : state) {
    state.PauseTiming();
    std::vector<MemoryTrace> segment;
    for (size_t i = 0; i < kSegment; ++i) {
      segment.push_back(
          filled.source.NextTrace("robot-new", filled.next_seq++));
    }
    state.ResumeTiming();
    ConsolidationResult result = filled.memory->Consolidate(
        std::move(segment), filled.next_cluster, filled.rng);
    filled.next_cluster += result.added.size();
    benchmark::DoNotOptimize(result);
  }
  state.counters["traces"] = static_cast<double>(filled.memory->trace_count());
  state.counters["clusters"] =
      static_cast<double>(filled.memory->clusters().size());
}

void BM_SampleReplay(benchmark::State& state) {
  Filled& filled = Memory(static_cast<size_t>(state.range(0)), false);
  for (auto _ : state) {
    benchmark::DoNotOptimize(filled.memory->SampleForReplay(1000, filled.rng));
  }
}

// The previous SampleForReplay: every weight recomputed and keyed.
void BM_SampleReplayScan(benchmark::State& state) {
  Filled& filled = Memory(static_cast<size_t>(state.range(0)), false);
  const MemoryOptions& options = filled.memory->options();
  for (auto _ : state) {
    std::vector<const MemoryTrace*> all;
    all.reserve(filled.memory->trace_count());
    for (const auto& [id, cluster] : filled.memory->clusters()) {
      for (const MemoryTrace& trace : cluster.traces) all.push_back(&trace);
    }
    std::vector<double> weights(all.size());
    for (size_t i = 0; i < all.size(); ++i) {
      weights[i] = ReplayWeight(all[i]->reward, all[i]->replay_count,
                                options.replay_decay, options.reward_floor);
    }
    std::vector<MemoryTrace> out;
    for (size_t i : SampleWithoutReplacement(weights, 1000, filled.rng)) {
      out.push_back(*all[i]);
    }
    benchmark::DoNotOptimize(out);
  }
}

void BM_Stats(benchmark::State& state) {
  Filled& filled = Memory(static_cast<size_t>(state.range(0)), false);
  for (auto _ : state) {
    std::map<std::string, uint64_t> robots, domains;
    for (const auto& [robot, n] : filled.memory->traces_by_robot()) {
      robots[robot] = n;
    }
    for (const auto& [domain, n] : filled.memory->traces_by_domain()) {
      domains[domain] = n;
    }
    benchmark::DoNotOptimize(robots);
    benchmark::DoNotOptimize(domains);
  }
}

void BM_StatsScan(benchmark::State& state) {
  Filled& filled = Memory(static_cast<size_t>(state.range(0)), false);
  for (auto _ : state) {
    std::map<std::string, uint64_t> robots, domains;
    for (const auto& [id, cluster] : filled.memory->clusters()) {
      for (const MemoryTrace& trace : cluster.traces) {
        ++robots[trace.robot_id];
        ++domains[trace.domain];
      }
    }
    benchmark::DoNotOptimize(robots);
    benchmark::DoNotOptimize(domains);
  }
}

// What a restart costs in the static memory: every cluster of a full
// memory put back with Restore (sum tree, counts, forgetting's closest-pair
// graph over the K centroids). The clusters are copied outside the timing.
void BM_Restore(benchmark::State& state) {
  Filled& filled = Memory(static_cast<size_t>(state.range(0)), false);
  for (auto _ : state) {
    state.PauseTiming();
    std::vector<Cluster> clusters;
    clusters.reserve(filled.memory->clusters().size());
    for (const auto& [id, cluster] : filled.memory->clusters()) {
      clusters.push_back(cluster);
    }
    auto memory = std::make_unique<StaticMemory>(filled.memory->options());
    state.ResumeTiming();
    for (Cluster& cluster : clusters) memory->Restore(std::move(cluster));
    state.PauseTiming();
    memory.reset();
    state.ResumeTiming();
  }
}

void BM_KMeansSegment(benchmark::State& state) {
  const MemoryOptions options;
  std::mt19937_64 data(5);
  std::normal_distribution<float> normal;
  std::vector<Eigen::MatrixXf> segments;
  for (int s = 0; s < 16; ++s) {
    Eigen::MatrixXf points(256 + 3, static_cast<Eigen::Index>(kSegment));
    for (size_t i = 0; i < kSegment; ++i) {
      MemoryTrace trace;
      trace.code.resize(256);
      for (float& v : trace.code) v = normal(data);
      trace.place.x = 2.0 * static_cast<double>(s * kSegment + i);
      points.col(static_cast<Eigen::Index>(i)) =
          FeatureSpatialCode(trace, options.spatial_scale_m);
    }
    segments.push_back(std::move(points));
  }
  std::mt19937_64 rng(3);
  size_t next = 0;
  double iterations = 0;
  for (auto _ : state) {
    const KMeansResult result =
        KMeans(segments[next++ % segments.size()], options.clusters_per_batch,
               options.kmeans_max_iterations, rng);
    iterations += result.iterations;
  }
  state.counters["iterations"] =
      iterations / static_cast<double>(state.iterations());
  state.counters["us_per_trace"] = benchmark::Counter(
      static_cast<double>(state.iterations() * kSegment),
      benchmark::Counter::kIsRate | benchmark::Counter::kInvert);
}

BENCHMARK(BM_KMeansSegment)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Consolidate)
    ->ArgsProduct({{5'000, 100'000, 1'000'000}, {0}})
    ->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Consolidate)
    ->ArgsProduct({{5'000, 100'000}, {1}})
    ->Unit(benchmark::kMillisecond);
BENCHMARK(BM_SampleReplay)
    ->Arg(5'000)
    ->Arg(100'000)
    ->Arg(1'000'000)
    ->Unit(benchmark::kMillisecond);
BENCHMARK(BM_SampleReplayScan)
    ->Arg(5'000)
    ->Arg(100'000)
    ->Arg(1'000'000)
    ->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Stats)->Arg(5'000)->Arg(100'000)->Arg(1'000'000)->Unit(
    benchmark::kMillisecond);
BENCHMARK(BM_StatsScan)
    ->Arg(5'000)
    ->Arg(100'000)
    ->Arg(1'000'000)
    ->Unit(benchmark::kMillisecond);
BENCHMARK(BM_Restore)
    ->Arg(100'000)
    ->Arg(1'000'000)
    ->Iterations(1)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace fleetmem::core

int main(int argc, char** argv) {
  return fleetmem::bench::Main(
      argc, argv, "fleetmem_memory_scale_bench",
      "static-memory costs against memory size (consolidation, forgetting, "
      "replay sampling, statistics).");
}
