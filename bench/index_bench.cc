// Exact vs FLANN place index on 256-d unit vectors drawn from 50 gaussian
// blobs (places seen several times), at static-memory sizes 1,000 to 100,000.
//
//   build/bin/fleetmem_index_bench --benchmark_min_time=0.2
//
// Query: one Search, k = 5, over a fixed set of queries from the same
// distribution; FLANN's recall@5 against the exact index is the `recall@5`
// counter (mean |approximate top-5 ∩ exact top-5| / 5).
// Add: one batch of 200 vectors (a consolidated segment) into an index of
// the size; Remove: one batch of 50 (a forgotten cluster). The index returns
// to its size between iterations, outside the timing.
// Build: Add of the whole memory into an empty index (loading a fleet).
// QueryFlannChecks: FLANN's `checks` at 5,000 vectors.
#include <benchmark/benchmark.h>

#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <iostream>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <utility>
#include <vector>

#include "bench/bench_main.h"
#include "services/engine/place_index.h"
#include "services/index/exact_index.h"
#include "services/index/flann_index.h"

namespace fleetmem::index {
namespace {

using engine::Neighbor;
using engine::PlaceIndex;
using Vector = std::vector<float>;

constexpr size_t kDimension = 256;
constexpr size_t kBlobs = 50;
constexpr float kSpread = 0.6f;  // expected norm of the noise around a centre
constexpr size_t kQueries = 500;
constexpr size_t kK = 5;
constexpr size_t kAddBatch = 200;
constexpr size_t kRemoveBatch = 50;

Vector Normalized(Vector v) {
  double norm = 0;
  for (float x : v) norm += double{x} * x;
  norm = std::sqrt(norm);
  for (float& x : v) x = static_cast<float>(x / norm);
  return v;
}

// Unit vectors: a random unit centre plus gaussian noise, normalised.
class BlobSource {
 public:
  explicit BlobSource(uint32_t seed) : rng_(seed) {
    std::normal_distribution<float> normal(0.0f, 1.0f);
    for (size_t b = 0; b < kBlobs; ++b) {
      Vector centre(kDimension);
      for (float& x : centre) x = normal(rng_);
      centres_.push_back(Normalized(std::move(centre)));
    }
  }
  Vector Next() {
    std::uniform_int_distribution<size_t> pick(0, kBlobs - 1);
    std::normal_distribution<float> noise(
        0.0f, kSpread / std::sqrt(static_cast<float>(kDimension)));
    Vector v = centres_[pick(rng_)];
    for (float& x : v) x += noise(rng_);
    return Normalized(std::move(v));
  }
  std::vector<Vector> Next(size_t count) {
    std::vector<Vector> vectors;
    for (size_t i = 0; i < count; ++i) vectors.push_back(Next());
    return vectors;
  }

 private:
  std::mt19937 rng_;
  std::vector<Vector> centres_;
};

constexpr uint32_t kSeed = 1234;  // the same blobs everywhere

// The vectors of a memory of `size` (ids 0..size-1), and the queries.
struct Dataset {
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
  std::vector<Vector> queries;
};

const Dataset& GetDataset(size_t size) {
  static std::map<size_t, std::unique_ptr<Dataset>> datasets;
  std::unique_ptr<Dataset>& dataset = datasets[size];
  if (dataset == nullptr) {
    dataset = std::make_unique<Dataset>();
    BlobSource source(kSeed);
    for (uint64_t id = 0; id < size; ++id) dataset->ids.push_back(id);
    dataset->vectors = source.Next(size);
    dataset->queries = source.Next(kQueries);
  }
  return *dataset;
}

enum class Kind { kExact, kFlann };

std::unique_ptr<PlaceIndex> NewIndex(Kind kind) {
  return kind == Kind::kExact ? NewExactIndex(kDimension)
                              : NewFlannIndex(kDimension);
}

void Check(const absl::Status& status) {
  if (!status.ok()) {
    std::cerr << status << "\n";
    std::abort();
  }
}

std::unique_ptr<PlaceIndex> Filled(Kind kind, size_t size) {
  const Dataset& data = GetDataset(size);
  std::unique_ptr<PlaceIndex> index = NewIndex(kind);
  Check(index->Add(data.ids, data.vectors));
  return index;
}

// Built once per (kind, size) and shared by the query benchmarks.
PlaceIndex& SharedIndex(Kind kind, size_t size) {
  static std::map<std::pair<Kind, size_t>, std::unique_ptr<PlaceIndex>> indexes;
  std::unique_ptr<PlaceIndex>& index = indexes[{kind, size}];
  if (index == nullptr) index = Filled(kind, size);
  return *index;
}

std::vector<Neighbor> SearchOrDie(const PlaceIndex& index, const Vector& query,
                                  size_t k) {
  engine::SearchParams params;
  params.k = k;
  absl::StatusOr<std::vector<Neighbor>> result = index.Search(query, params);
  Check(result.status());
  return *std::move(result);
}

double RecallAt(const PlaceIndex& index, const PlaceIndex& exact,
                const std::vector<Vector>& queries, size_t k) {
  double recall = 0;
  for (const Vector& query : queries) {
    std::set<uint64_t> truth;
    for (const Neighbor& n : SearchOrDie(exact, query, k)) truth.insert(n.id);
    size_t hits = 0;
    for (const Neighbor& n : SearchOrDie(index, query, k)) {
      hits += truth.contains(n.id);
    }
    recall += static_cast<double>(hits) / k;
  }
  return recall / queries.size();
}

void BM_Query(benchmark::State& state, Kind kind) {
  const size_t size = state.range(0);
  const Dataset& data = GetDataset(size);
  const PlaceIndex& index = SharedIndex(kind, size);
  size_t q = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(SearchOrDie(index, data.queries[q], kK));
    q = (q + 1) % data.queries.size();
  }
  state.counters["recall@5"] =
      kind == Kind::kExact
          ? 1.0
          : RecallAt(index, SharedIndex(Kind::kExact, size), data.queries, kK);
}

// New vectors for every batch: re-adding identical vectors would pile them
// up in FLANN's trees (removed points stay there until a rebuild).
void BM_Add(benchmark::State& state, Kind kind) {
  const size_t size = state.range(0);
  std::unique_ptr<PlaceIndex> index = Filled(kind, size);
  BlobSource source(kSeed);
  std::vector<uint64_t> ids(kAddBatch);
  std::vector<Vector> vectors = source.Next(kAddBatch);
  uint64_t next_id = size;
  for (auto _ : state) {
    for (uint64_t& id : ids) id = next_id++;
    Check(index->Add(ids, vectors));
    state.PauseTiming();
    Check(index->Remove(ids));
    vectors = source.Next(kAddBatch);
    state.ResumeTiming();
  }
  state.SetItemsProcessed(state.iterations() * kAddBatch);
}

void BM_Remove(benchmark::State& state, Kind kind) {
  const size_t size = state.range(0);
  const Dataset& data = GetDataset(size);
  std::unique_ptr<PlaceIndex> index = Filled(kind, size);
  BlobSource source(kSeed);
  // Removes 50 ids and adds 50 new vectors under new ids.
  std::vector<uint64_t> ids(data.ids.begin(), data.ids.begin() + kRemoveBatch);
  uint64_t next_id = size;
  for (auto _ : state) {
    Check(index->Remove(ids));
    state.PauseTiming();
    for (uint64_t& id : ids) id = next_id++;
    Check(index->Add(ids, source.Next(kRemoveBatch)));
    state.ResumeTiming();
  }
  state.SetItemsProcessed(state.iterations() * kRemoveBatch);
}

void BM_Build(benchmark::State& state, Kind kind) {
  const size_t size = state.range(0);
  GetDataset(size);
  for (auto _ : state) {
    benchmark::DoNotOptimize(Filled(kind, size));
  }
  state.SetItemsProcessed(state.iterations() * size);
}

// FLANN's recall/latency knob at the default static memory's capacity.
void BM_QueryFlannChecks(benchmark::State& state) {
  constexpr size_t kSize = 5000;
  const Dataset& data = GetDataset(kSize);
  FlannIndexOptions options;
  options.checks = static_cast<int>(state.range(0));
  std::unique_ptr<PlaceIndex> index = NewFlannIndex(kDimension, options);
  Check(index->Add(data.ids, data.vectors));
  size_t q = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(SearchOrDie(*index, data.queries[q], kK));
    q = (q + 1) % data.queries.size();
  }
  state.counters["recall@5"] =
      RecallAt(*index, SharedIndex(Kind::kExact, kSize), data.queries, kK);
}
BENCHMARK(BM_QueryFlannChecks)
    ->Arg(32)
    ->Arg(128)
    ->Arg(512)
    ->Arg(2048)
    ->Unit(benchmark::kMicrosecond);

void Sizes(benchmark::internal::Benchmark* b) {
  for (int64_t size : {1000, 5000, 20000, 100000}) b->Arg(size);
}

BENCHMARK_CAPTURE(BM_Query, exact, Kind::kExact)
    ->Apply(Sizes)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Query, flann, Kind::kFlann)
    ->Apply(Sizes)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Add, exact, Kind::kExact)
    ->Apply(Sizes)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Add, flann, Kind::kFlann)
    ->Apply(Sizes)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Remove, exact, Kind::kExact)
    ->Apply(Sizes)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Remove, flann, Kind::kFlann)
    ->Apply(Sizes)
    ->Unit(benchmark::kMicrosecond);
BENCHMARK_CAPTURE(BM_Build, exact, Kind::kExact)
    ->Apply(Sizes)
    ->Unit(benchmark::kMillisecond);
BENCHMARK_CAPTURE(BM_Build, flann, Kind::kFlann)
    ->Apply(Sizes)
    ->Unit(benchmark::kMillisecond);

}  // namespace
}  // namespace fleetmem::index

int main(int argc, char** argv) {
  return fleetmem::bench::Main(argc, argv, "fleetmem_index_bench",
                               "exact against FLANN place index: query "
                               "latency, recall@5, Add/Remove and build cost.");
}
