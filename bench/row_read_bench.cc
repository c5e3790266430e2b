// Reading an int8 graph's floats (rows of 257 floats, a 256-d code and its
// scale) out of their file, as a query's rescoring (40 rows) and a sample's
// codes (1,000 rows) read them: one row at a time (`Read`, the build before
// issue 49's seventh round) against one `Gather` of all of them (the rows
// the page cache holds copied at once, the reads of the others started
// together, then waited for), in the same run, from the page cache
// ("warm": rows of the first 100,000, read beforehand) and off it ("cold":
// the file written back and dropped from the page cache before each batch).
// The file holds 1,000,000 rows (1 GB) in $TMPDIR (/tmp by default);
// random rows, the same ones for both ways.
//
//   build/bin/fleetmem_row_read_bench --benchmark_min_time=2
#include <benchmark/benchmark.h>
#include <fcntl.h>
#include <stdlib.h>
#include <unistd.h>

#include <cstdint>
#include <cstdlib>
#include <filesystem>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "bench/bench_main.h"
#include "services/index/float_file.h"

namespace fleetmem::index {
namespace {

constexpr size_t kWidth = 257;
constexpr size_t kRows = 1'000'000;
constexpr size_t kWarmRows = 100'000;

// The benchmark's file of kRows random rows, made once.
struct RowFile {
  RowFile() {
    const char* tmp = std::getenv("TMPDIR");
    directory = std::string(tmp != nullptr ? tmp : "/tmp") + "/rows-XXXXXX";
    if (::mkdtemp(directory.data()) == nullptr) std::abort();
    rows = std::make_unique<FileFloatRows>(directory, kWidth);
    rows->Reserve(kRows);
    std::mt19937 rng(7);
    std::normal_distribution<float> normal;
    std::vector<float> chunk(4096 * kWidth);
    for (size_t first = 0; first < kRows; first += 4096) {
      for (float& value : chunk) value = normal(rng);
      rows->Write(first, 4096, chunk.data());
    }
    // The file is unlinked: its descriptor is found among this process's.
    const std::string made =
        std::filesystem::canonical(directory).string() + "/graph-floats-";
    for (const auto& entry :
         std::filesystem::directory_iterator("/proc/self/fd")) {
      std::error_code error;
      const std::string target =
          std::filesystem::read_symlink(entry.path(), error).string();
      if (!error && target.rfind(made, 0) == 0) {
        fd = std::stoi(entry.path().filename().string());
      }
    }
    if (fd < 0) std::abort();
  }
  ~RowFile() {
    rows.reset();
    std::filesystem::remove_all(directory);
  }
  // Writes the file back and drops it from the page cache.
  void Drop() const {
    ::fdatasync(fd);
    ::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED);
  }
  // Reads the first kWarmRows rows into the page cache.
  void Warm() const {
    std::vector<float> chunk(4096 * kWidth);
    for (size_t first = 0; first < kWarmRows; first += 4096) {
      rows->Read(first, 4096, chunk.data());
    }
  }

  std::string directory;
  std::unique_ptr<FileFloatRows> rows;
  int fd = -1;
};

RowFile& File() {
  static RowFile* file = new RowFile();  // lives as long as the process
  return *file;
}

// Args: rows a batch, gathered (1) or read one at a time (0), cold (1) or
// warm (0).
void BM_RowBatch(benchmark::State& state) {
  const auto batch = static_cast<size_t>(state.range(0));
  const bool gathered = state.range(1) == 1;
  const bool cold = state.range(2) == 1;
  RowFile& file = File();
  if (!cold) file.Warm();
  std::mt19937_64 rng(11);
  std::vector<uint32_t> rows(batch);
  std::vector<float> values(batch * kWidth);
  for (auto _ : state) {
    state.PauseTiming();
    for (uint32_t& row : rows) {
      row = static_cast<uint32_t>(rng() % (cold ? kRows : kWarmRows));
    }
    if (cold) file.Drop();
    state.ResumeTiming();
    if (gathered) {
      file.rows->Gather(rows, values.data());
    } else {
      for (size_t i = 0; i < batch; ++i) {
        file.rows->Read(rows[i], 1, values.data() + i * kWidth);
      }
    }
    benchmark::DoNotOptimize(values.data());
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(batch));
}
BENCHMARK(BM_RowBatch)
    ->ArgNames({"rows", "gathered", "cold"})
    ->ArgsProduct({{40, 1000}, {0, 1}, {0, 1}})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

}  // namespace
}  // namespace fleetmem::index

int main(int argc, char** argv) {
  return fleetmem::bench::Main(
      argc, argv, "fleetmem_row_read_bench",
      "reading a graph's floats from their file: one row at a time against "
      "one Gather of a batch, from the page cache and off it.");
}
