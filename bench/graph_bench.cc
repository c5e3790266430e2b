// The place graph against hnswlib (issue 49: "hnswlib (float) beside the
// quantized graph for insert rate and recall/QPS"): the same N 256-d codes
// (bench_data.h, unit length) inserted into
//   hnswlib   hnswlib's HierarchicalNSW<float> used directly (L2 space),
//             addPoint on `threads` threads, as python3-hnswlib's add_items
//   float     fleetmem's HNSW index (index::NewHnswIndex, codes kFloat):
//             AddNormalized in batches of 50,000 (an import's build step),
//             linked on `threads` insert threads
//   int8      the same with codes kInt8 (quantized walk, float rescoring)
//   int8-file the same with the floats in a file (HnswIndexOptions::
//             floats_dir, --floats-dir: the server's default), so that
//             rescoring reads its candidates' rows with pread
// at the same M and ef_construction, one kind after the other on the idle
// machine; then each answers 1,000 queries (k = 10) one at a time on one
// thread at each ef_search, and 200 of them are scored against the exact
// top 10 (a scan of the floats). One CSV row per kind and ef_search:
//
//   fleetmem_graph_bench --size 100000 --out graph.csv
//
// insert_ratio and qps_ratio divide by hnswlib's (the goal: the insert
// rate >= 1.5x hnswlib's, recall@10 >= 0.95 at a QPS >= hnswlib's).
// graph_mb is what each holds for vectors and links (hnswlib: its nodes
// and upper layers; fleetmem: core::HnswGraph::MemoryBytes, the floats kept
// beside int8 nodes included; int8-file's floats are the page cache's, not
// counted).
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_format.h"
#include "bench/bench_data.h"
#include "hnswlib/hnswlib.h"
#include "services/common/cli_program.h"
#include "services/index/hnsw_index.h"

namespace fleetmem::bench {
namespace {

using Clock = std::chrono::steady_clock;
constexpr size_t kDimension = 256;
constexpr size_t kK = 10;
constexpr size_t kRecallQueries = 200;
constexpr size_t kBuildStep = 50'000;

double SecondsSince(Clock::time_point start) {
  return std::chrono::duration<double>(Clock::now() - start).count();
}

struct Settings {
  size_t size = 100'000;
  size_t threads = 2;
  size_t m = 16;
  size_t ef_construction = 40;
  size_t queries = 1000;
  size_t rescore_oversample = 4;
  std::vector<size_t> ef_search = {64, 128, 256};
  std::vector<std::string> kinds = {"hnswlib", "float", "int8"};
  std::string floats_dir = "/tmp";
};

// One kind under test: built, then searched at a given ef_search.
class Subject {
 public:
  virtual ~Subject() = default;
  virtual void Build(const std::vector<std::vector<float>>& codes) = 0;
  virtual void SetEf(size_t ef) = 0;
  virtual std::vector<uint64_t> Search(const std::vector<float>& query) = 0;
  virtual double Bytes() const = 0;
};

class Hnswlib final : public Subject {
 public:
  explicit Hnswlib(const Settings& s)
      : settings_(s),
        space_(kDimension),
        hnsw_(&space_, s.size, s.m, s.ef_construction, 42) {}
  void Build(const std::vector<std::vector<float>>& codes) override {
    std::atomic<size_t> next{0};
    auto insert = [&] {
      for (size_t i; (i = next.fetch_add(1)) < codes.size();) {
        hnsw_.addPoint(codes[i].data(), i);
      }
    };
    std::vector<std::thread> helpers;
    for (size_t t = 1; t < settings_.threads; ++t) helpers.emplace_back(insert);
    insert();
    for (std::thread& helper : helpers) helper.join();
  }
  void SetEf(size_t ef) override { hnsw_.setEf(ef); }
  std::vector<uint64_t> Search(const std::vector<float>& query) override {
    auto found = hnsw_.searchKnn(query.data(), kK);
    std::vector<uint64_t> ids;
    for (; !found.empty(); found.pop()) ids.push_back(found.top().second);
    return ids;
  }
  double Bytes() const override {
    double bytes = static_cast<double>(hnsw_.cur_element_count) *
                   static_cast<double>(hnsw_.size_data_per_element_);
    for (size_t i = 0; i < hnsw_.cur_element_count; ++i) {
      bytes += static_cast<double>(hnsw_.element_levels_[i] *
                                   hnsw_.size_links_per_element_);
    }
    return bytes;
  }

 private:
  Settings settings_;
  hnswlib::L2Space space_;
  hnswlib::HierarchicalNSW<float> hnsw_;
};

class Fleetmem final : public Subject {
 public:
  Fleetmem(const Settings& s, index::HnswIndexOptions::Codes codes,
           std::string floats_dir = "") {
    index::HnswIndexOptions options;
    options.m = s.m;
    options.ef_construction = s.ef_construction;
    options.insert_threads = s.threads;
    options.codes = codes;
    options.rescore_oversample = s.rescore_oversample;
    options.floats_dir = std::move(floats_dir);
    index_ = index::NewHnswIndex(kDimension, options);
  }
  void Build(const std::vector<std::vector<float>>& codes) override {
    for (size_t first = 0; first < codes.size(); first += kBuildStep) {
      const size_t count = std::min(kBuildStep, codes.size() - first);
      std::vector<uint64_t> ids(count);
      std::vector<std::span<const float>> spans(count);
      for (size_t i = 0; i < count; ++i) {
        ids[i] = first + i;
        spans[i] = codes[first + i];
      }
      if (absl::Status added = index_->AddNormalized(ids, spans); !added.ok()) {
        std::cerr << "graph_bench: " << added << "\n";
        std::exit(1);
      }
    }
  }
  void SetEf(size_t ef) override { index::SetHnswEfSearch(*index_, ef); }
  std::vector<uint64_t> Search(const std::vector<float>& query) override {
    engine::SearchParams params;
    params.k = kK;
    params.unit_query = true;
    const std::vector<engine::Neighbor> found =
        index_->Search(query, params).value();
    std::vector<uint64_t> ids;
    for (const engine::Neighbor& n : found) ids.push_back(n.id);
    return ids;
  }
  double Bytes() const override {
    return static_cast<double>(index::HnswMemoryBytes(*index_));
  }

 private:
  std::unique_ptr<engine::PlaceIndex> index_;
};

// The exact top kK of each query among `codes` (squared distances, on
// `threads` threads).
std::vector<std::set<uint64_t>> Truth(
    const std::vector<std::vector<float>>& codes,
    const std::vector<std::vector<float>>& queries, size_t threads) {
  std::vector<std::set<uint64_t>> truth(queries.size());
  std::atomic<size_t> next{0};
  auto work = [&] {
    for (size_t q; (q = next.fetch_add(1)) < queries.size();) {
      std::vector<std::pair<float, uint64_t>> all(codes.size());
      for (size_t i = 0; i < codes.size(); ++i) {
        float d = 0;
        for (size_t j = 0; j < kDimension; ++j) {
          const float x = codes[i][j] - queries[q][j];
          d += x * x;
        }
        all[i] = {d, i};
      }
      std::partial_sort(all.begin(), all.begin() + kK, all.end());
      for (size_t i = 0; i < kK; ++i) truth[q].insert(all[i].second);
    }
  };
  std::vector<std::thread> helpers;
  for (size_t t = 1; t < threads; ++t) helpers.emplace_back(work);
  work();
  for (std::thread& helper : helpers) helper.join();
  return truth;
}

struct Built {
  std::string kind;
  double seconds = 0;
};

int Run(const Settings& s, const std::string& out_path) {
  CodeSource source(kDimension, 3);
  std::vector<std::vector<float>> codes(s.size), queries(s.queries);
  for (auto& code : codes) code = source.Next();
  for (auto& query : queries) query = source.Next();
  std::cerr << "graph_bench: exact answers of " << kRecallQueries
            << " queries over " << s.size << " codes\n";
  const std::vector<std::vector<float>> recall_queries(
      queries.begin(), queries.begin() + std::min(kRecallQueries, s.queries));
  const auto truth = Truth(codes, recall_queries, s.threads);

  std::ofstream out(out_path);
  out << "kind,size,threads,m,ef_construction,build_s,insert_per_s,"
         "insert_ratio,graph_mb,ef_search,recall10,qps,qps_ratio\n";
  double hnswlib_rate = 0;
  std::vector<double> hnswlib_qps(s.ef_search.size(), 0.0);
  for (const std::string& kind : s.kinds) {
    std::unique_ptr<Subject> subject;
    if (kind == "hnswlib") subject = std::make_unique<Hnswlib>(s);
    if (kind == "float") {
      subject =
          std::make_unique<Fleetmem>(s, index::HnswIndexOptions::Codes::kFloat);
    }
    if (kind == "int8") {
      subject =
          std::make_unique<Fleetmem>(s, index::HnswIndexOptions::Codes::kInt8);
    }
    if (kind == "int8-file") {
      subject = std::make_unique<Fleetmem>(
          s, index::HnswIndexOptions::Codes::kInt8, s.floats_dir);
    }
    const auto start = Clock::now();
    subject->Build(codes);
    const double seconds = SecondsSince(start);
    const double rate = static_cast<double>(s.size) / seconds;
    if (kind == "hnswlib") hnswlib_rate = rate;
    std::cerr << absl::StrFormat("graph_bench: %s built in %.1f s (%.0f/s)\n",
                                 kind, seconds, rate);
    for (size_t e = 0; e < s.ef_search.size(); ++e) {
      subject->SetEf(s.ef_search[e]);
      double hits = 0;
      for (size_t q = 0; q < recall_queries.size(); ++q) {
        for (uint64_t id : subject->Search(recall_queries[q])) {
          hits += static_cast<double>(truth[q].count(id));
        }
      }
      const auto timed = Clock::now();
      for (const auto& query : queries) subject->Search(query);
      const double qps =
          static_cast<double>(queries.size()) / SecondsSince(timed);
      if (kind == "hnswlib") hnswlib_qps[e] = qps;
      const double recall =
          hits / static_cast<double>(recall_queries.size() * kK);
      out << absl::StrFormat(
          "%s,%d,%d,%d,%d,%.2f,%.0f,%.3f,%.1f,%d,%.4f,%.0f,%.3f\n", kind,
          s.size, s.threads, s.m, s.ef_construction, seconds, rate,
          hnswlib_rate > 0 ? rate / hnswlib_rate : 0.0, subject->Bytes() / 1e6,
          s.ef_search[e], recall, qps,
          hnswlib_qps[e] > 0 ? qps / hnswlib_qps[e] : 0.0);
      std::cerr << absl::StrFormat(
          "graph_bench: %s ef_search %d: recall@10 %.4f, %.0f queries/s\n",
          kind, s.ef_search[e], recall, qps);
    }
  }
  return out ? 0 : 1;
}

}  // namespace
}  // namespace fleetmem::bench

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem_graph_bench: the place graph (float and int8 codes) against "
      "hnswlib on the same codes: insert rate, recall@10 and queries/s."};
  fleetmem::common::SetUpProgram(app, "fleetmem_graph_bench");
  fleetmem::bench::Settings s;
  std::string out = "graph_bench.csv";
  app.add_option("--size", s.size, "codes inserted")->capture_default_str();
  app.add_option("--threads", s.threads, "insert threads of every kind")
      ->capture_default_str();
  app.add_option("--m", s.m, "HNSW M")->capture_default_str();
  app.add_option("--ef-construction", s.ef_construction, "HNSW ef_construction")
      ->capture_default_str();
  app.add_option("--queries", s.queries, "queries timed per ef_search")
      ->capture_default_str();
  app.add_option("--rescore-oversample", s.rescore_oversample,
                 "int8: candidates rescored per neighbour")
      ->capture_default_str();
  app.add_option("--ef-search", s.ef_search, "search breadths")
      ->delimiter(',')
      ->capture_default_str();
  app.add_option("--floats-dir", s.floats_dir,
                 "int8-file: the directory of its floats' file")
      ->capture_default_str();
  app.add_option("--kinds", s.kinds, "hnswlib, float, int8, int8-file")
      ->delimiter(',')
      ->check(CLI::IsMember({"hnswlib", "float", "int8", "int8-file"}))
      ->capture_default_str();
  app.add_option("--out", out, "CSV written")->capture_default_str();
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  if (s.size < 100 || s.queries < 1 || s.threads < 1) {
    std::cerr << "fleetmem_graph_bench: error: --size >= 100, --queries and "
                 "--threads >= 1\n";
    return 2;
  }
  return fleetmem::bench::Run(s, out);
}
