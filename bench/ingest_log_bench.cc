// The ingest log's append (an upload's acknowledgement waits for it): the
// segment log (services/storage/segment_log.h) against the synced RocksDB
// write batch it replaced, the same encoded entries in the same run.
//
//   build/bin/fleetmem_ingest_log_bench [--benchmark_filter=...]
// Each iteration appends one entry of N traces of 256-d and returns once it
// is durable (fdatasync / WriteOptions::sync). Files go under $TMPDIR (or
// /tmp): run it on the filesystem the data dir is on.
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "bench/bench_main.h"
#include "benchmark/benchmark.h"
#include "rocksdb/db.h"
#include "services/core/types.h"
#include "services/storage/record_codec.h"
#include "services/storage/segment_log.h"

namespace fleetmem::storage {
namespace {

std::vector<core::MemoryTrace> Entry(int traces) {
  std::vector<core::MemoryTrace> out(traces);
  for (int i = 0; i < traces; ++i) {
    out[i].robot_id = "robot-0";
    out[i].seq = static_cast<uint64_t>(i) + 1;
    out[i].code.assign(256, 0.001f * static_cast<float>(i % 97));
    out[i].encoder_version = "bench";
  }
  return out;
}

std::string FreshDirectory(const std::string& name) {
  const char* tmp = std::getenv("TMPDIR");
  const std::string path =
      std::string(tmp != nullptr ? tmp : "/tmp") + "/fleetmem-" + name;
  std::filesystem::remove_all(path);
  std::filesystem::create_directories(path);
  return path;
}

void BM_SegmentLogAppend(benchmark::State& state) {
  const std::vector<core::MemoryTrace> traces =
      Entry(static_cast<int>(state.range(0)));
  const std::string path = FreshDirectory("segment-log-bench");
  SegmentLogOptions options;
  options.directory = path + "/log";
  absl::StatusOr<std::unique_ptr<SegmentLog>> log =
      SegmentLog::Open(std::move(options));
  if (!log.ok()) {
    state.SkipWithError(log.status().ToString().c_str());
    return;
  }
  for (auto _ : state) {
    const engine::LogAppend append{engine::UploadRecord{traces}};
    if (absl::StatusOr<std::vector<engine::AppendedEntry>> done =
            (*log)->Append("f", {&append, 1}, {});
        !done.ok()) {
      state.SkipWithError(done.status().ToString().c_str());
      break;
    }
  }
  state.SetItemsProcessed(state.iterations() * state.range(0));
  log->reset();
  std::filesystem::remove_all(path);
}
BENCHMARK(BM_SegmentLogAppend)->Arg(200)->Arg(500)->UseRealTime();

void BM_RocksDbSyncedAppend(benchmark::State& state) {
  const std::vector<core::MemoryTrace> traces =
      Entry(static_cast<int>(state.range(0)));
  const std::string path = FreshDirectory("rocksdb-log-bench");
  rocksdb::Options options;
  options.create_if_missing = true;
  rocksdb::DB* raw = nullptr;
  if (!rocksdb::DB::Open(options, path + "/db", &raw).ok()) {
    state.SkipWithError("cannot open RocksDB");
    return;
  }
  std::unique_ptr<rocksdb::DB> db(raw);
  rocksdb::WriteOptions synced;
  synced.sync = true;
  uint64_t sequence = 0;
  for (auto _ : state) {
    // As the RocksDB store wrote the log before the segment log: the
    // entry encoded, under a key of its sequence, in one synced batch.
    rocksdb::WriteBatch batch;
    const std::string key = "l/f/" + std::to_string(++sequence);
    batch.Put(key, EncodeLoggedRecord(engine::UploadRecord{traces}));
    if (!db->Write(synced, &batch).ok()) {
      state.SkipWithError("RocksDB write failed");
      break;
    }
  }
  state.SetItemsProcessed(state.iterations() * state.range(0));
  db.reset();
  std::filesystem::remove_all(path);
}
BENCHMARK(BM_RocksDbSyncedAppend)->Arg(200)->Arg(500)->UseRealTime();

}  // namespace
}  // namespace fleetmem::storage

int main(int argc, char** argv) {
  return fleetmem::bench::Main(argc, argv, "fleetmem_ingest_log_bench",
                               "the ingest log's durable append: the segment "
                               "log against a synced RocksDB write batch.");
}
