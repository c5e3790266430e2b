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
//   fleetmem-load soak --server ADDR --pid PID [--seconds S --interval S
//                      --rate T/s --peak-seconds S --report FILE]
//       measures the peak upload rate (when --rate is 0), then runs at half
//       of it with queries beside, printing RSS, open files and latencies
//       every interval (CSV to --report).
//
// Credentials as for `fleetmem`: --token-file / $FLEETMEM_TOKEN_FILE /
// $FLEETMEM_TOKEN, --tls-ca/--tls-cert/--tls-key.
#include <atomic>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <random>
#include <string>
#include <thread>

#include "CLI/CLI.hpp"
#include "absl/strings/str_format.h"
#include "clients/cpp/fleetmem_client.h"
#include "tools/load/load_generator.h"

namespace {

using fleetmem::load::LatencyLog;
using fleetmem::load::UploadLoadOptions;

struct Common {
  std::string server = "127.0.0.1:50051";
  std::string fleet = "load";
  int dimension = 128;
  fleetmem::client::CredentialSources credentials;
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
}

absl::StatusOr<fleetmem::client::ClientOptions> ClientFor(const Common& common,
                                                          int attempts) {
  fleetmem::client::ClientOptions options;
  options.target = common.server;
  options.max_attempts = attempts;
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

// Queries at about `rate` per second until `stop`, timing each.
void QueryLoop(const fleetmem::client::ClientOptions& options,
               const std::string& fleet, int dimension, double rate,
               const std::atomic<bool>& stop, LatencyLog* latencies) {
  std::unique_ptr<fleetmem::client::Client> client =
      fleetmem::client::Client::Create(options);
  std::mt19937_64 rng(7);
  uint64_t i = 0;
  while (!stop.load()) {
    fleetmem::v1::QueryPlaceRequest request;
    request.set_fleet_id(fleet);
    request.set_k(5);
    const fleetmem::v1::MemoryTrace probe =
        fleetmem::load::LoadTrace("load-0", 1 + rng() % 1000, dimension);
    *request.mutable_code() = probe.code();
    const auto sent = std::chrono::steady_clock::now();
    if (client->QueryPlace(request).ok()) {
      latencies->Add(std::chrono::duration<double, std::milli>(
                         std::chrono::steady_clock::now() - sent)
                         .count());
    }
    ++i;
    std::this_thread::sleep_for(std::chrono::duration<double>(1.0 / rate));
  }
}

int Soak(const Common& common, int pid, double seconds, double interval,
         double rate, double peak_seconds, int robots,
         const std::string& report) {
  absl::StatusOr<fleetmem::client::ClientOptions> options =
      ClientFor(common, 5);
  if (!options.ok()) return Fail(options.status());
  UploadLoadOptions load;
  load.fleet_id = common.fleet;
  load.dimension = common.dimension;
  load.robots = robots;
  uint64_t next_seq = 1;
  if (rate <= 0) {
    load.duration =
        std::chrono::milliseconds(static_cast<int64_t>(peak_seconds * 1000));
    absl::StatusOr<fleetmem::load::UploadLoadResult> peak =
        fleetmem::load::RunUploads(*options, load, "", nullptr, nullptr);
    if (!peak.ok()) return Fail(peak.status());
    const double peak_rate = peak->acknowledged / peak->seconds;
    rate = peak_rate / 2;
    for (uint64_t seq : peak->next_seq) next_seq = std::max(next_seq, seq);
    std::cout
        << absl::StrFormat(
               "peak: %.0f traces/s over %.1f s (%d robots, batch %d, dim %d); "
               "soak at half: %.0f traces/s\n",
               peak_rate, peak->seconds, robots, load.batch, load.dimension,
               rate)
        << std::flush;
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
    QueryLoop(*options, common.fleet, common.dimension, 20, stop, &queries);
  });
  std::ofstream csv;
  if (!report.empty()) {
    csv.open(report);
    csv << "elapsed_s,rss_mib,open_fds,upload_calls,upload_p50_ms,"
           "upload_p99_ms,upload_max_ms,query_calls,query_p50_ms,"
           "query_p99_ms\n";
  }
  std::cout << "elapsed_s  rss_mib  fds  uploads  up_p50  up_p99  up_max  "
               "queries  q_p50  q_p99\n";
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
    const LatencyLog::Summary up = uploads.Take();
    const LatencyLog::Summary q = queries.Take();
    const std::string row = absl::StrFormat(
        "%.0f,%.1f,%d,%zu,%.2f,%.2f,%.2f,%zu,%.2f,%.2f", elapsed,
        sample->rss_bytes / 1048576.0, sample->open_fds, up.count, up.p50,
        up.p99, up.max, q.count, q.p50, q.p99);
    std::cout << absl::StrFormat(
                     "%9.0f  %7.1f  %3d  %7zu  %6.2f  %6.2f  %6.2f  %7zu  "
                     "%5.2f  %5.2f\n",
                     elapsed, sample->rss_bytes / 1048576.0, sample->open_fds,
                     up.count, up.p50, up.p99, up.max, q.count, q.p50, q.p99)
              << std::flush;
    if (csv.is_open()) csv << row << "\n" << std::flush;
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

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"Load for a running fleetmem-server (crash trials, soak)."};
  app.require_subcommand(1);
  Common common;

  CLI::App* upload = app.add_subcommand("upload", "robots upload traces");
  AddCommon(upload, &common);
  UploadLoadOptions load;
  double seconds = 10;
  std::string ack_log;
  upload->add_option("--robots", load.robots, "robots (threads)");
  upload->add_option("--batch", load.batch, "traces per call");
  upload->add_option("--rate", load.rate, "traces/s in all; 0 = max");
  upload->add_option("--seconds", seconds, "how long");
  upload->add_option("--first-seq", load.first_seq, "first seq per robot");
  upload->add_option("--ack-log", ack_log, "append acknowledged batches");
  upload->add_flag("--stop-on-error", load.stop_on_error,
                   "stop a robot at its first failed call");

  CLI::App* verify =
      app.add_subcommand("verify", "every acknowledged trace is stored");
  AddCommon(verify, &common);
  verify->add_option("--ack-log", ack_log, "log of acknowledged batches")
      ->required();

  CLI::App* soak = app.add_subcommand("soak", "steady load with samples");
  AddCommon(soak, &common);
  int pid = 0, robots = 4;
  double soak_seconds = 3600, interval = 60, rate = 0, peak_seconds = 10;
  std::string report;
  soak->add_option("--pid", pid, "server process to sample")->required();
  soak->add_option("--seconds", soak_seconds, "duration (default 3600)");
  soak->add_option("--interval", interval, "seconds between samples");
  soak->add_option("--rate", rate, "traces/s; 0 = half the measured peak");
  soak->add_option("--peak-seconds", peak_seconds, "peak measurement time");
  soak->add_option("--robots", robots, "uploading robots");
  soak->add_option("--report", report, "CSV of the samples");

  CLI11_PARSE(app, argc, argv);

  if (upload->parsed()) {
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
  if (verify->parsed()) {
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
  return Soak(common, pid, soak_seconds, interval, rate, peak_seconds, robots,
              report);
}
