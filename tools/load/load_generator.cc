#include "tools/load/load_generator.h"

#include <dirent.h>

#include <algorithm>
#include <cmath>
#include <fstream>
#include <functional>
#include <random>
#include <sstream>
#include <thread>
#include <utility>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "httplib.h"

namespace fleetmem::load {
namespace {

std::string RobotName(int index) { return absl::StrCat("load-", index); }

std::vector<v1::MemoryTrace> Batch(const std::string& robot, uint64_t first,
                                   uint64_t last, int dimension) {
  std::vector<v1::MemoryTrace> traces;
  traces.reserve(last - first + 1);
  for (uint64_t seq = first; seq <= last; ++seq) {
    traces.push_back(LoadTrace(robot, seq, dimension));
  }
  return traces;
}

double Percentile(std::vector<double>& sorted, double q) {
  if (sorted.empty()) return 0;
  const size_t index = static_cast<size_t>(q * (sorted.size() - 1) + 0.5);
  return sorted[std::min(index, sorted.size() - 1)];
}

}  // namespace

v1::MemoryTrace LoadTrace(const std::string& robot_id, uint64_t seq,
                          int dimension) {
  std::mt19937_64 rng(std::hash<std::string>()(robot_id) * 1000003u ^ seq);
  std::normal_distribution<float> normal;
  v1::MemoryTrace trace;
  trace.set_robot_id(robot_id);
  trace.set_seq(seq);
  trace.set_domain("load");
  trace.set_encoder_version("load-v1");
  for (int i = 0; i < dimension; ++i) trace.add_code(normal(rng));
  trace.mutable_pose()->set_x(static_cast<double>(seq) * 2.0);
  trace.mutable_pose()->set_y(static_cast<double>(robot_id.size()) * 100.0);
  std::uniform_real_distribution<float> reward(0.0f, 1.0f);
  trace.set_reward(reward(rng));
  trace.set_timestamp_ns(static_cast<int64_t>(seq) * 1'000'000);
  return trace;
}

void LatencyLog::Add(double ms) {
  std::lock_guard<std::mutex> lock(mu_);
  ms_.push_back(ms);
}

LatencyLog::Summary LatencyLog::Take() {
  std::vector<double> taken;
  {
    std::lock_guard<std::mutex> lock(mu_);
    taken.swap(ms_);
  }
  std::sort(taken.begin(), taken.end());
  Summary summary;
  summary.count = taken.size();
  summary.p50 = Percentile(taken, 0.5);
  summary.p90 = Percentile(taken, 0.9);
  summary.p99 = Percentile(taken, 0.99);
  summary.p999 = Percentile(taken, 0.999);
  summary.max = taken.empty() ? 0 : taken.back();
  return summary;
}

namespace {

// A robot's `size` distinct traces whose codes its batches reuse (none for
// 0: every trace its own code).
std::vector<v1::MemoryTrace> CodePool(const std::string& robot, int size,
                                      int dimension) {
  std::vector<v1::MemoryTrace> pool;
  for (int i = 0; i < size; ++i) {
    pool.push_back(LoadTrace(robot, static_cast<uint64_t>(i) + 1, dimension));
  }
  return pool;
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
      .count();
}

// Seqs first..last with the pool's codes in turn.
std::vector<v1::MemoryTrace> FromPool(const std::vector<v1::MemoryTrace>& pool,
                                      uint64_t first, uint64_t last) {
  std::vector<v1::MemoryTrace> traces;
  traces.reserve(last - first + 1);
  for (uint64_t seq = first; seq <= last; ++seq) {
    traces.push_back(pool[seq % pool.size()]);
    traces.back().set_seq(seq);
  }
  return traces;
}

}  // namespace

absl::StatusOr<UploadLoadResult> RunUploads(const client::ClientOptions& client,
                                            const UploadLoadOptions& options,
                                            const std::string& ack_log,
                                            const std::atomic<bool>* stop,
                                            LatencyLog* latencies) {
  if (options.robots < 1 || options.batch < 1 || options.dimension < 1) {
    return absl::InvalidArgumentError(
        "robots, batch and dimension must be >= 1");
  }
  std::ofstream log;  // the acknowledged batches, when asked for
  if (!ack_log.empty()) {
    log.open(ack_log, std::ios::app);
    if (!log) return absl::NotFoundError("cannot open " + ack_log);
  }
  std::mutex mu;  // guards log and result
  UploadLoadResult result;
  result.next_seq.assign(options.robots, options.first_seq);
  const auto start = std::chrono::steady_clock::now();
  const auto end = start + options.duration;
  // Each robot sends a batch every `interval` (rate shared by the robots).
  const std::chrono::duration<double> interval(
      options.rate > 0 ? options.batch * options.robots / options.rate : 0.0);
  std::vector<std::thread> threads;
  for (int r = 0; r < options.robots; ++r) {
    threads.emplace_back([&, r] {
      std::unique_ptr<client::Client> connection =
          client::Client::Create(client);
      const std::string robot = RobotName(r);
      uint64_t next = options.first_seq;
      const std::vector<v1::MemoryTrace> pool =
          CodePool(robot, options.code_pool, options.dimension);
      auto due = std::chrono::steady_clock::now();
      while (std::chrono::steady_clock::now() < end &&
             !(stop != nullptr && stop->load())) {
        if (options.max_traces > 0) {
          std::lock_guard<std::mutex> lock(mu);
          if (result.acknowledged >= options.max_traces) break;
        }
        if (interval.count() > 0) {
          std::this_thread::sleep_until(due);
          due +=
              std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                  interval);
        }
        const uint64_t last = next + options.batch - 1;
        const std::vector<v1::MemoryTrace> traces =
            pool.empty() ? Batch(robot, next, last, options.dimension)
                         : FromPool(pool, next, last);
        const auto sent = std::chrono::steady_clock::now();
        absl::StatusOr<v1::UploadTracesResponse> reply =
            connection->Upload(options.fleet_id, traces);
        const double ms = std::chrono::duration<double, std::milli>(
                              std::chrono::steady_clock::now() - sent)
                              .count();
        if (latencies != nullptr) latencies->Add(ms);
        std::lock_guard<std::mutex> lock(mu);
        if (!reply.ok()) {
          ++result.failed_calls;
          if (result.first_error.empty()) {
            result.first_error = reply.status().ToString();
          }
          if (options.stop_on_error) break;
          continue;  // the same batch again
        }
        result.acknowledged += traces.size();
        if (log.is_open()) {
          log << robot << " " << next << " " << last << "\n";
          log.flush();
        }
        next = last + 1;
      }
      std::lock_guard<std::mutex> lock(mu);
      result.next_seq[r] = next;
    });
  }
  for (std::thread& thread : threads) thread.join();
  result.seconds = SecondsSince(start);
  return result;
}

absl::StatusOr<VerifyResult> VerifyAcknowledged(
    const client::ClientOptions& client, const std::string& fleet_id,
    int dimension, const std::string& ack_log) {
  std::ifstream in(ack_log);
  if (!in) return absl::NotFoundError("cannot read " + ack_log);
  std::unique_ptr<client::Client> connection = client::Client::Create(client);
  VerifyResult result;
  std::string line;
  while (std::getline(in, line)) {
    std::istringstream fields(line);
    std::string robot;
    uint64_t first = 0, last = 0;
    if (!(fields >> robot >> first >> last) || last < first) {
      return absl::InvalidArgumentError(
          absl::StrCat(ack_log, ": bad line \"", line, "\""));
    }
    absl::StatusOr<v1::UploadTracesResponse> reply =
        connection->Upload(fleet_id, Batch(robot, first, last, dimension));
    if (!reply.ok()) return reply.status();
    result.acknowledged += last - first + 1;
    result.present += reply->duplicates();
    result.lost += reply->accepted();
  }
  return result;
}

absl::StatusOr<ProcessSample> SampleProcess(int pid) {
  ProcessSample sample;
  std::ifstream status(absl::StrCat("/proc/", pid, "/status"));
  if (!status) return absl::NotFoundError(absl::StrCat("no process ", pid));
  std::string line;
  while (std::getline(status, line)) {
    if (line.rfind("VmRSS:", 0) == 0) {
      sample.rss_bytes = std::stoull(line.substr(6)) * 1024;
    }
  }
  const std::string fd_dir = absl::StrCat("/proc/", pid, "/fd");
  if (DIR* dir = opendir(fd_dir.c_str())) {
    while (dirent* entry = readdir(dir)) {
      if (entry->d_name[0] != '.') ++sample.open_fds;
    }
    closedir(dir);
  }
  return sample;
}

absl::StatusOr<std::map<std::string, double>> ScrapeMetrics(
    const std::string& http_address) {
  const size_t colon = http_address.rfind(':');
  int port = 0;
  if (colon == std::string::npos ||
      !absl::SimpleAtoi(http_address.substr(colon + 1), &port)) {
    return absl::InvalidArgumentError(
        absl::StrCat("not HOST:PORT: \"", http_address, "\""));
  }
  httplib::Client client(http_address.substr(0, colon), port);
  client.set_read_timeout(10);
  const httplib::Result got = client.Get("/metrics");
  if (!got || got->status != 200) {
    return absl::UnavailableError(
        absl::StrCat("GET http://", http_address, "/metrics: ",
                     got ? absl::StrCat("status ", got->status)
                         : httplib::to_string(got.error())));
  }
  std::map<std::string, double> samples;
  for (absl::string_view line : absl::StrSplit(got->body, '\n')) {
    if (line.empty() || line[0] == '#') continue;
    // "series value": label values never hold a space here (fleet ids,
    // methods, kinds), so the value follows the last space.
    const size_t space = line.rfind(' ');
    double value = 0;
    if (space == absl::string_view::npos ||
        !absl::SimpleAtod(line.substr(space + 1), &value)) {
      continue;
    }
    samples[std::string(line.substr(0, space))] = value;
  }
  return samples;
}

}  // namespace fleetmem::load
