// fleetmem-load: load for a running fleetmem-server.
//
//   fleetmem-load upload --server ADDR [--robots N --batch B --rate T/s
//                        --seconds S --first-seq N --ack-log FILE
//                        --stop-on-error]
//       robots upload until the time is up; with --ack-log every batch the
//       server acknowledged is logged (crash trials).
//   fleetmem-load verify --server ADDR --ack-log FILE
//       re-sends every logged batch: each trace must come back as a
//       duplicate; exit 1 if any was lost.
//   fleetmem-load bench --server ADDR [--robots N --batch B --dimension D
//                       --seconds S --query-rate Q --sample-rate S
//                       --peer ADDR --durable-peer-dir DIR --csv FILE]
//       the same load against the server and against the bare gRPC peer
//       (discarding uploads; started in this process unless --peer), and
//       with --durable-peer-dir against the durable peer (each message
//       appended and fdatasynced, one at a time), printed with the ratios:
//       upload throughput and latency percentiles per call.
//   fleetmem-load peer [--listen ADDR --durable-file FILE]
//       serves a peer alone.
//   fleetmem-load soak --server ADDR --pid PID [--seconds S --interval S
//                      --rate T/s --peak-seconds S --report FILE
//                      --metrics HTTP_ADDR]
//       measures the peak upload rate (when --rate is 0), then runs at half
//       of it with queries beside, printing RSS, open files and latencies
//       every interval (CSV to --report); with --metrics, also the heap and
//       RocksDB's memory from the server's /metrics (what RSS is made of).
//
// Credentials as for `fleetmem`: --token-file / $FLEETMEM_TOKEN_FILE /
// $FLEETMEM_TOKEN, --tls-ca/--tls-cert/--tls-key.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <map>
#include <random>
#include <string>
#include <string_view>
#include <thread>
#include <utility>

#include "CLI/CLI.hpp"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_replace.h"
#include "clients/cpp/fleetmem_client.h"
#include "fleetmem_version.h"
#include "services/common/cli_program.h"
#include "tools/load/load_generator.h"
#include "tools/load/peer_server.h"

namespace {

using fleetmem::load::LatencyLog;
using fleetmem::load::UploadLoadOptions;

struct Common {
  std::string server = "127.0.0.1:50051";
  std::string fleet = "load";
  int dimension = 128;
  fleetmem::client::CredentialSources credentials;
  // When uploads are answered: at the durable append (the load a robot
  // fleet makes) or once applied.
  std::string ack = "durable";
};

void AddCommon(CLI::App* app, Common* common) {
  app->add_option("--server", common->server, "HOST:PORT");
  app->add_option("--fleet", common->fleet, "fleet id");
  app->add_option("--dimension", common->dimension, "code dimension");
  app->add_option("--token-file", common->credentials.token_file,
                  "file with the token NAME:SECRET");
  app->add_option("--tls-ca", common->credentials.ca_file, "server CA (PEM)");
  app->add_option("--tls-cert", common->credentials.cert_file,
                  "client certificate (PEM)");
  app->add_option("--tls-key", common->credentials.key_file, "client key");
  app->add_option("--ack", common->ack,
                  "uploads answered when durable (default) or applied")
      ->check(CLI::IsMember({"durable", "applied"}));
}

absl::StatusOr<fleetmem::client::ClientOptions> ClientFor(const Common& common,
                                                          int attempts) {
  fleetmem::client::ClientOptions options;
  options.target = common.server;
  options.max_attempts = attempts;
  options.upload_ack = common.ack == "applied"
                           ? fleetmem::v1::UPLOAD_ACK_APPLIED
                           : fleetmem::v1::UPLOAD_ACK_DURABLE;
  if (absl::Status loaded =
          fleetmem::client::LoadCredentials(common.credentials, &options);
      !loaded.ok()) {
    return loaded;
  }
  return options;
}

int Fail(const absl::Status& status) {
  std::cerr << "fleetmem-load: " << status << "\n";
  return 1;
}

// A call at about `rate` per second until `stop`, timing each (QueryPlace or
// SampleReplay of the load's fleet).
enum class Call { kQuery, kSample, kStats };

void CallLoop(const fleetmem::client::ClientOptions& options,
              const std::string& fleet, int dimension, double rate, Call call,
              const std::atomic<bool>& stop, LatencyLog* latencies) {
  std::unique_ptr<fleetmem::client::Client> client =
      fleetmem::client::Client::Create(options);
  std::mt19937_64 rng(7);
  auto due = std::chrono::steady_clock::now();
  const auto interval =
      std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(1.0 / rate));
  while (!stop.load()) {
    std::this_thread::sleep_until(due);
    due += interval;
    const auto sent = std::chrono::steady_clock::now();
    bool ok;
    if (call == Call::kStats) {
      ok = client->GetStats(fleet).ok();
    } else if (call == Call::kQuery) {
      fleetmem::v1::QueryPlaceRequest request;
      request.set_fleet_id(fleet);
      request.set_k(10);
      *request.mutable_code() =
          fleetmem::load::LoadTrace("load-0", 1 + rng() % 1000, dimension)
              .code();
      ok = client->QueryPlace(request).ok();
    } else {
      ok = client->SampleReplay(fleet, "load-sampler", 1000).ok();
    }
    if (ok) {
      latencies->Add(std::chrono::duration<double, std::milli>(
                         std::chrono::steady_clock::now() - sent)
                         .count());
    }
  }
}

struct SoakOptions {
  int pid = 0;               // the server's process
  double seconds = 3600;     // duration of the soak
  double interval = 60;      // seconds between samples
  double rate = 0;           // traces/s; 0: half the measured peak
  double peak_seconds = 10;  // peak measurement time
  int robots = 4;
  std::string report;   // CSV of the samples; empty: none
  std::string metrics;  // the server's HTTP HOST:PORT; empty: no scrape
};

// The memory series of the server's /metrics that a soak sample shows, in
// MiB, with their CSV column names.
constexpr std::pair<const char*, const char*> kMemorySeries[] = {
    {"heap_in_use_mib", "fleetmem_heap_bytes{kind=\"in_use\"}"},
    {"heap_free_mib", "fleetmem_heap_bytes{kind=\"free\"}"},
    {"memtables_mib", "fleetmem_store_memory_bytes{kind=\"memtables\"}"},
    {"table_readers_mib",
     "fleetmem_store_memory_bytes{kind=\"table_readers\"}"},
    {"block_cache_mib", "fleetmem_store_memory_bytes{kind=\"block_cache\"}"},
    {"store_disk_mib", "fleetmem_store_disk_bytes"},
};

// The rate a soak runs at: half the peak that `load` reaches in
// `peak_seconds` (said on stdout); `next_seq` gets the seq the soak goes
// on from.
absl::StatusOr<double> HalfThePeak(
    const fleetmem::client::ClientOptions& options, UploadLoadOptions load,
    double peak_seconds, uint64_t* next_seq) {
  load.duration =
      std::chrono::milliseconds(static_cast<int64_t>(peak_seconds * 1000));
  absl::StatusOr<fleetmem::load::UploadLoadResult> peak =
      fleetmem::load::RunUploads(options, load, "", nullptr, nullptr);
  if (!peak.ok()) return peak.status();
  const double peak_rate = peak->acknowledged / peak->seconds;
  for (uint64_t seq : peak->next_seq) *next_seq = std::max(*next_seq, seq);
  std::cout << absl::StrFormat(
                   "peak: %.0f traces/s over %.1f s (%d robots, batch %d, dim "
                   "%d); soak at half: %.0f traces/s\n",
                   peak_rate, peak->seconds, load.robots, load.batch,
                   load.dimension, peak_rate / 2)
            << std::flush;
  return peak_rate / 2;
}

// The server's memory series (kMemorySeries) from its /metrics at
// `metrics`, in MiB, appended as CSV columns to `row` and as aligned
// columns to `line`.
absl::Status ScrapeMemory(const std::string& metrics, std::string* row,
                          std::string* line) {
  absl::StatusOr<std::map<std::string, double>> scraped =
      fleetmem::load::ScrapeMetrics(metrics);
  if (!scraped.ok()) return scraped.status();
  for (const auto& [column, series] : kMemorySeries) {
    const auto found = scraped->find(series);
    const double mib = found == scraped->end() ? -1 : found->second / 1048576.0;
    absl::StrAppendFormat(row, ",%.1f", mib);
    absl::StrAppendFormat(line, "  %*.1f",
                          static_cast<int>(std::string_view(column).size()),
                          mib);
  }
  return absl::OkStatus();
}

// The soak's table header on stdout, and its CSV at soak.report (if set)
// opened in `csv` with its header.
void StartReport(const SoakOptions& soak, std::ofstream* csv) {
  std::string memory_header;
  if (!soak.metrics.empty()) {
    for (const auto& [column, series] : kMemorySeries) {
      absl::StrAppend(&memory_header, ",", column);
    }
  }
  if (!soak.report.empty()) {
    csv->open(soak.report);
    *csv << "elapsed_s,rss_mib,open_fds,upload_calls,upload_p50_ms,"
            "upload_p99_ms,upload_max_ms,query_calls,query_p50_ms,"
            "query_p99_ms"
         << memory_header << "\n";
  }
  std::cout << "elapsed_s  rss_mib  fds  uploads  up_p50  up_p99  up_max  "
               "queries  q_p50  q_p99"
            << absl::StrReplaceAll(memory_header, {{",", "  "}}) << "\n";
}

// One sample of the soak: a line on stdout and a row of `csv` (if open).
void WriteSample(double elapsed, const fleetmem::load::ProcessSample& sample,
                 const LatencyLog::Summary& up, const LatencyLog::Summary& q,
                 const std::string& memory_row, const std::string& memory_line,
                 std::ofstream& csv) {
  std::cout << absl::StrFormat(
                   "%9.0f  %7.1f  %3d  %7zu  %6.2f  %6.2f  %6.2f  %7zu  "
                   "%5.2f  %5.2f%s\n",
                   elapsed, sample.rss_bytes / 1048576.0, sample.open_fds,
                   up.count, up.p50, up.p99, up.max, q.count, q.p50, q.p99,
                   memory_line)
            << std::flush;
  if (!csv.is_open()) return;
  csv << absl::StrFormat("%.0f,%.1f,%d,%zu,%.2f,%.2f,%.2f,%zu,%.2f,%.2f%s",
                         elapsed, sample.rss_bytes / 1048576.0, sample.open_fds,
                         up.count, up.p50, up.p99, up.max, q.count, q.p50,
                         q.p99, memory_row)
      << "\n"
      << std::flush;
}

int Soak(const Common& common, const SoakOptions& soak) {
  const int pid = soak.pid;
  const double seconds = soak.seconds, interval = soak.interval;
  const int robots = soak.robots;
  double rate = soak.rate;
  absl::StatusOr<fleetmem::client::ClientOptions> options =
      ClientFor(common, 5);
  if (!options.ok()) return Fail(options.status());
  UploadLoadOptions load;
  load.fleet_id = common.fleet;
  load.dimension = common.dimension;
  load.robots = robots;
  uint64_t next_seq = 1;
  if (rate <= 0) {
    absl::StatusOr<double> peak =
        HalfThePeak(*options, load, soak.peak_seconds, &next_seq);
    if (!peak.ok()) return Fail(peak.status());
    rate = *peak;
  }
  load.rate = rate;
  load.first_seq = next_seq;
  load.duration =
      std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000));
  std::atomic<bool> stop{false};
  LatencyLog uploads, queries;
  fleetmem::load::UploadLoadResult result;
  std::thread uploader([&] {
    absl::StatusOr<fleetmem::load::UploadLoadResult> run =
        fleetmem::load::RunUploads(*options, load, "", &stop, &uploads);
    if (run.ok()) result = *run;
  });
  std::thread querier([&] {
    CallLoop(*options, common.fleet, common.dimension, 20, Call::kQuery, stop,
             &queries);
  });
  std::ofstream csv;
  StartReport(soak, &csv);
  const auto start = std::chrono::steady_clock::now();
  int exit_code = 0;
  for (double elapsed = 0; elapsed < seconds;) {
    std::this_thread::sleep_for(
        std::chrono::duration<double>(std::min(interval, seconds - elapsed)));
    elapsed =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
            .count();
    absl::StatusOr<fleetmem::load::ProcessSample> sample =
        fleetmem::load::SampleProcess(pid);
    if (!sample.ok()) {
      std::cerr << "fleetmem-load: the server is gone: " << sample.status()
                << "\n";
      exit_code = 1;
      break;
    }
    std::string memory_row, memory_line;
    if (!soak.metrics.empty()) {
      if (absl::Status scraped =
              ScrapeMemory(soak.metrics, &memory_row, &memory_line);
          !scraped.ok()) {
        std::cerr << "fleetmem-load: " << scraped << "\n";
        exit_code = 1;
        break;
      }
    }
    WriteSample(elapsed, *sample, uploads.Take(), queries.Take(), memory_row,
                memory_line, csv);
  }
  stop = true;
  uploader.join();
  querier.join();
  std::cout << absl::StrFormat(
      "soak: %llu traces acknowledged in %.0f s (%.0f/s), %llu failed "
      "calls%s\n",
      static_cast<unsigned long long>(result.acknowledged), result.seconds,
      result.seconds > 0 ? result.acknowledged / result.seconds : 0.0,
      static_cast<unsigned long long>(result.failed_calls),
      result.first_error.empty() ? "" : " (first: " + result.first_error + ")");
  return exit_code;
}

struct PhaseResult {
  std::string target;
  double upload_rate = 0;  // traces/s acknowledged
  LatencyLog::Summary upload, query, sample, stats;
  uint64_t failed = 0;
  std::string first_error;
};

// The same load against one target: robots uploading as fast as they can,
// queries and samples at their rates beside them.
absl::StatusOr<PhaseResult> RunPhase(const std::string& name,
                                     fleetmem::client::ClientOptions options,
                                     UploadLoadOptions load, double query_rate,
                                     double sample_rate, double stats_rate) {
  std::atomic<bool> stop{false};
  LatencyLog uploads, queries, samples, stats;
  absl::StatusOr<fleetmem::load::UploadLoadResult> run;
  std::thread uploader([&] {
    if (load.robots > 0) {
      run = fleetmem::load::RunUploads(options, load, "", &stop, &uploads);
    } else {  // calls only
      std::this_thread::sleep_for(load.duration);
      run = fleetmem::load::UploadLoadResult{};
      run->seconds = std::chrono::duration<double>(load.duration).count();
    }
    stop = true;
  });
  std::vector<std::thread> callers;
  if (query_rate > 0) {
    callers.emplace_back([&] {
      CallLoop(options, load.fleet_id, load.dimension, query_rate, Call::kQuery,
               stop, &queries);
    });
  }
  if (sample_rate > 0) {
    callers.emplace_back([&] {
      CallLoop(options, load.fleet_id, load.dimension, sample_rate,
               Call::kSample, stop, &samples);
    });
  }
  if (stats_rate > 0) {
    callers.emplace_back([&] {
      CallLoop(options, load.fleet_id, load.dimension, stats_rate, Call::kStats,
               stop, &stats);
    });
  }
  uploader.join();
  for (std::thread& caller : callers) caller.join();
  if (!run.ok()) return run.status();
  PhaseResult result;
  result.target = name;
  result.upload_rate = run->acknowledged / std::max(run->seconds, 1e-9);
  result.upload = uploads.Take();
  result.query = queries.Take();
  result.sample = samples.Take();
  result.stats = stats.Take();
  result.failed = run->failed_calls;
  result.first_error = run->first_error;
  return result;
}

// Bench's results (fleetmem's first, then the bare peer's, then the durable
// peer's if it ran): a table with the ratios to the peers, and as CSV at
// `csv_path` (if set). The exit code.
int Report(const std::vector<PhaseResult>& results,
           const UploadLoadOptions& load, double seconds,
           const std::string& csv_path) {
  std::cout << absl::StrFormat(
      "%-9s %10s %8s %8s %8s %9s %9s %10s %10s %9s %9s\n", "target",
      "uploads/s", "up p50", "up p99", "up p99.9", "query p50", "query p99",
      "sample p50", "sample p99", "stats p50", "stats p99");
  for (const PhaseResult& r : results) {
    std::cout << absl::StrFormat(
        "%-9s %10.0f %8.2f %8.2f %8.2f %9.3f %9.3f %10.3f %10.3f %9.3f %9.3f\n",
        r.target, r.upload_rate, r.upload.p50, r.upload.p99, r.upload.p999,
        r.query.p50, r.query.p99, r.sample.p50, r.sample.p99, r.stats.p50,
        r.stats.p99);
  }
  const auto ratio_to = [&](size_t peer, const PhaseResult& r) {
    return peer < results.size()
               ? r.upload_rate / std::max(results[peer].upload_rate, 1e-9)
               : 0.0;
  };
  for (size_t peer = 1; peer < results.size(); ++peer) {
    std::cout << absl::StrFormat(
        "fleetmem/%s upload throughput: %.3f (%.0f vs %.0f traces/s; "
        "latencies in ms)\n",
        results[peer].target, ratio_to(peer, results[0]),
        results[0].upload_rate, results[peer].upload_rate);
  }
  for (const PhaseResult& r : results) {
    if (r.failed > 0) {
      std::cout << r.target << ": " << r.failed
                << " failed upload calls; first: " << r.first_error << "\n";
    }
  }
  if (!csv_path.empty()) {
    std::ofstream csv(csv_path);
    csv << "target,streams,batch,dimension,seconds,uploads_per_s,"
           "upload_p50_ms,upload_p90_ms,upload_p99_ms,upload_p999_ms,"
           "upload_max_ms,query_calls,query_p50_ms,query_p99_ms,sample_calls,"
           "sample_p50_ms,sample_p99_ms,stats_calls,stats_p50_ms,stats_p99_ms,"
           "ratio_to_peer,ratio_to_durable\n";
    for (const PhaseResult& r : results) {
      csv << absl::StrFormat(
          "%s,%d,%d,%d,%.1f,%.1f,%.4f,%.4f,%.4f,%.4f,%.4f,%u,%.4f,%.4f,%u,"
          "%.4f,%.4f,%u,%.4f,%.4f,%.4f,%s\n",
          r.target, load.robots, load.batch, load.dimension, seconds,
          r.upload_rate, r.upload.p50, r.upload.p90, r.upload.p99,
          r.upload.p999, r.upload.max, r.query.count, r.query.p50, r.query.p99,
          r.sample.count, r.sample.p50, r.sample.p99, r.stats.count,
          r.stats.p50, r.stats.p99, ratio_to(1, r),
          results.size() > 2 ? absl::StrFormat("%.4f", ratio_to(2, r)) : "");
    }
    if (!csv) return Fail(absl::DataLossError("cannot write " + csv_path));
  }
  return 0;
}

// fleetmem-load bench: the load against the bare gRPC peer (started in this
// process unless --peer names one), with `durable_dir` against the durable
// peer (started in this process, its file in that directory), then against
// the server, as a table with the ratios, and as CSV.
int Bench(const Common& common, UploadLoadOptions load, double seconds,
          double query_rate, double sample_rate, double stats_rate,
          const std::string& peer_address, const std::string& durable_dir,
          const std::string& csv_path) {
  absl::StatusOr<fleetmem::client::ClientOptions> options =
      ClientFor(common, 1);
  if (!options.ok()) return Fail(options.status());
  load.fleet_id = common.fleet;
  load.dimension = common.dimension;
  load.duration =
      std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000));
  if (load.code_pool == 0) load.code_pool = 1000;
  std::unique_ptr<fleetmem::load::PeerServer> peer;
  fleetmem::client::ClientOptions peer_options = *options;
  if (peer_address.empty()) {
    absl::StatusOr<std::unique_ptr<fleetmem::load::PeerServer>> started =
        fleetmem::load::PeerServer::Start("127.0.0.1:0");
    if (!started.ok()) return Fail(started.status());
    peer = *std::move(started);
    peer_options.target = peer->address();
  } else {
    peer_options.target = peer_address;
  }
  std::vector<std::pair<std::string, fleetmem::client::ClientOptions>> targets =
      {{"fleetmem", *options}, {"peer", peer_options}};
  std::unique_ptr<fleetmem::load::PeerServer> durable;
  if (!durable_dir.empty()) {
    absl::StatusOr<std::unique_ptr<fleetmem::load::PeerServer>> started =
        fleetmem::load::PeerServer::Start(
            "127.0.0.1:0", {.durable_file = durable_dir + "/durable-peer.log"});
    if (!started.ok()) return Fail(started.status());
    durable = *std::move(started);
    targets.emplace_back("durable", *options);
    targets.back().second.target = durable->address();
  }
  // The peers run first, on an idle machine: a server still applying the
  // backlog of its own phase would take CPU from a peer run after it. The
  // results keep fleetmem's first.
  std::rotate(targets.begin(), targets.begin() + 1, targets.end());
  std::vector<PhaseResult> results;
  for (const auto& [name, target] : targets) {
    std::cerr << "fleetmem-load bench: " << load.robots << " stream(s), batch "
              << load.batch << ", " << load.dimension << "-d, " << seconds
              << " s against " << name << " (" << target.target << ")\n";
    absl::StatusOr<PhaseResult> phase =
        RunPhase(name, target, load, query_rate, sample_rate, stats_rate);
    if (!phase.ok()) return Fail(phase.status());
    results.push_back(*phase);
    // The next phase continues the robots' seqs (no duplicates).
    load.first_seq += 100'000'000;
  }
  std::rotate(results.rbegin(), results.rbegin() + 1, results.rend());
  return Report(results, load, seconds, csv_path);
}

// `upload`: robots upload traces (the crash trials' load).
struct UploadCommand {
  CLI::App* app = nullptr;
  UploadLoadOptions load;
  double seconds = 10;
  std::string ack_log;

  void Add(CLI::App& parent, Common* common) {
    app = parent.add_subcommand("upload", "robots upload traces");
    AddCommon(app, common);
    app->add_option("--robots", load.robots, "robots (threads)");
    app->add_option("--batch", load.batch, "traces per call");
    app->add_option("--rate", load.rate, "traces/s in all; 0 = max");
    app->add_option("--seconds", seconds, "how long");
    app->add_option("--first-seq", load.first_seq, "first seq per robot");
    app->add_option("--ack-log", ack_log, "append acknowledged batches");
    app->add_option("--traces", load.max_traces,
                    "stop after this many acknowledged traces (all robots)");
    app->add_option("--code-pool", load.code_pool,
                    "distinct codes per robot (0: every trace its own)");
    app->add_flag("--stop-on-error", load.stop_on_error,
                  "stop a robot at its first failed call");
  }

  int Run(const Common& common) {
    absl::StatusOr<fleetmem::client::ClientOptions> options =
        ClientFor(common, load.stop_on_error ? 1 : 5);
    if (!options.ok()) return Fail(options.status());
    load.fleet_id = common.fleet;
    load.dimension = common.dimension;
    load.duration =
        std::chrono::milliseconds(static_cast<int64_t>(seconds * 1000));
    absl::StatusOr<fleetmem::load::UploadLoadResult> result =
        fleetmem::load::RunUploads(*options, load, ack_log, nullptr, nullptr);
    if (!result.ok()) return Fail(result.status());
    uint64_t next = 0;
    for (uint64_t seq : result->next_seq) next = std::max(next, seq);
    std::cout << absl::StrFormat(
        "acknowledged %llu traces in %.2f s (%.0f/s); %llu failed calls; "
        "next seq %llu%s\n",
        static_cast<unsigned long long>(result->acknowledged), result->seconds,
        result->acknowledged / std::max(result->seconds, 1e-9),
        static_cast<unsigned long long>(result->failed_calls),
        static_cast<unsigned long long>(next),
        result->first_error.empty() ? ""
                                    : "; first error: " + result->first_error);
    return 0;
  }
};

// `verify`: every acknowledged trace of an upload's log is stored.
struct VerifyCommand {
  CLI::App* app = nullptr;
  std::string ack_log;

  void Add(CLI::App& parent, Common* common) {
    app = parent.add_subcommand("verify", "every acknowledged trace is stored");
    AddCommon(app, common);
    app->add_option("--ack-log", ack_log, "log of acknowledged batches")
        ->required();
  }

  int Run(const Common& common) const {
    absl::StatusOr<fleetmem::client::ClientOptions> options =
        ClientFor(common, 5);
    if (!options.ok()) return Fail(options.status());
    absl::StatusOr<fleetmem::load::VerifyResult> result =
        fleetmem::load::VerifyAcknowledged(*options, common.fleet,
                                           common.dimension, ack_log);
    if (!result.ok()) return Fail(result.status());
    std::cout << absl::StrFormat(
        "acknowledged %llu, stored %llu, lost %llu\n",
        static_cast<unsigned long long>(result->acknowledged),
        static_cast<unsigned long long>(result->present),
        static_cast<unsigned long long>(result->lost));
    return result->lost == 0 && result->present == result->acknowledged ? 0 : 1;
  }
};

// `soak`: steady load with samples of the server's memory.
struct SoakCommand {
  CLI::App* app = nullptr;
  SoakOptions options;

  void Add(CLI::App& parent, Common* common) {
    app = parent.add_subcommand("soak", "steady load with samples");
    AddCommon(app, common);
    app->add_option("--pid", options.pid, "server process to sample")
        ->required();
    app->add_option("--seconds", options.seconds, "duration (default 3600)");
    app->add_option("--interval", options.interval, "seconds between samples");
    app->add_option("--rate", options.rate,
                    "traces/s; 0 = half the measured peak");
    app->add_option("--peak-seconds", options.peak_seconds,
                    "peak measurement time");
    app->add_option("--robots", options.robots, "uploading robots");
    app->add_option("--report", options.report, "CSV of the samples");
    app->add_option("--metrics", options.metrics,
                    "the server's HTTP HOST:PORT: sample its memory series");
  }
};

// `bench`: throughput and latency against the bare gRPC peer.
struct BenchCommand {
  CLI::App* app = nullptr;
  UploadLoadOptions load;
  double seconds = 10, query_rate = 0, sample_rate = 0, stats_rate = 0;
  std::string peer_address, durable_dir, csv_path;

  void Add(CLI::App& parent, Common* common) {
    app = parent.add_subcommand("bench",
                                "throughput and latency against the peers");
    AddCommon(app, common);
    app->add_option("--robots", load.robots,
                    "upload streams (0: only the other calls)")
        ->check(CLI::Range(0, 1024));
    app->add_option("--batch", load.batch, "traces per call")
        ->check(CLI::Range(1, 100000));
    app->add_option("--seconds", seconds, "per target")
        ->check(CLI::Range(0.001, 1e6));
    app->add_option("--first-seq", load.first_seq, "first seq per robot");
    app->add_option("--query-rate", query_rate, "QueryPlace calls/s beside");
    app->add_option("--sample-rate", sample_rate,
                    "SampleReplay calls/s beside");
    app->add_option("--stats-rate", stats_rate, "GetStats calls/s beside");
    app->add_option("--code-pool", load.code_pool,
                    "distinct codes per robot (default 1000)")
        ->check(CLI::NonNegativeNumber);
    app->add_option("--peer", peer_address,
                    "HOST:PORT of a running `fleetmem-load peer` (default: "
                    "one started in this process)");
    app->add_option("--durable-peer-dir", durable_dir,
                    "also run against the durable peer (each upload message "
                    "appended to a file in DIR and fdatasynced, one at a "
                    "time)")
        ->check(CLI::ExistingDirectory);
    app->add_option("--csv", csv_path, "write the results as CSV");
  }

  int Run(const Common& common) const {
    return Bench(common, load, seconds, query_rate, sample_rate, stats_rate,
                 peer_address, durable_dir, csv_path);
  }
};

// `peer`: the bare gRPC peer, until killed.
struct PeerCommand {
  CLI::App* app = nullptr;
  std::string listen = "127.0.0.1:50061";
  fleetmem::load::PeerOptions options;

  void Add(CLI::App& parent) {
    app = parent.add_subcommand(
        "peer", "serve the bare gRPC peer (discards uploads) until killed");
    app->add_option("--listen", listen, "HOST:PORT");
    app->add_option("--durable-file", options.durable_file,
                    "the durable peer: append each upload message to FILE "
                    "(made or truncated) and fdatasync it before answering");
  }

  int Run() const {
    absl::StatusOr<std::unique_ptr<fleetmem::load::PeerServer>> server =
        fleetmem::load::PeerServer::Start(listen, options);
    if (!server.ok()) return Fail(server.status());
    std::cout << "peer listening on " << (*server)->address() << std::endl;
    (*server)->Wait();
    return 0;
  }
};

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem-load: load for a running fleetmem-server (crash trials, "
      "soak, benchmarks)."};
  fleetmem::common::SetUpProgram(app, "fleetmem-load");
  app.require_subcommand(1);
  Common common;
  UploadCommand upload;
  upload.Add(app, &common);
  VerifyCommand verify;
  verify.Add(app, &common);
  SoakCommand soak;
  soak.Add(app, &common);
  BenchCommand bench;
  bench.Add(app, &common);
  PeerCommand peer;
  peer.Add(app);
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  if (bench.app->parsed()) return bench.Run(common);
  if (peer.app->parsed()) return peer.Run();
  if (upload.app->parsed()) return upload.Run(common);
  if (verify.app->parsed()) return verify.Run(common);
  return Soak(common, soak.options);
}
