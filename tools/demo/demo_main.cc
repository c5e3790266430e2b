// fleetmem-demo: a fleet of robots builds one shared memory from the real
// Nordland summer images, then recognises the same places in winter.
//
//   1. Each robot (a thread with its own client) drives a different stretch
//      of the summer route: it encodes every frame with a classical holistic
//      image code, computes honest rewards (rewards.h) and uploads its memory
//      traces in batches. The server consolidates each robot's segment of
//      200 traces as it arrives (k-means, downsampling) and forgets clusters
//      beyond K_max.
//   2. A final Consolidate takes the rest; each robot then samples replay
//      traces from the fleet memory (fleet sharing: peers' places too).
//   3. The winter frames of the same stretches query the fleet memory
//      (k = 6): recall@1, recall@5 and weighted recall WR. The same queries
//      against every uploaded code by brute force are the unbounded baseline.
//
//   fleetmem-demo [--server HOST:PORT] [--data DIR] [--fleet ID]
//                 [--robots N] [--stretch-length N] [--results-md FILE]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <mutex>
#include <numeric>
#include <random>
#include <span>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/usage.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "clients/cpp/fleetmem_client.h"
#include "services/core/place_metrics.h"
#include "tools/demo/code_search.h"
#include "tools/demo/command_line.h"
#include "tools/demo/image_encoder.h"
#include "tools/demo/nordland.h"
#include "tools/demo/rewards.h"

ABSL_FLAG(std::string, server, "127.0.0.1:50051", "fleetmem server, HOST:PORT");
ABSL_FLAG(std::string, data, FLEETMEM_DATA_DIR,
          "shared data folder (holds nordland/summer and nordland/winter)");
ABSL_FLAG(std::string, fleet, "",
          "fleet id (default: nordland-demo-<UTC time>, so reruns do not "
          "collide)");
ABSL_FLAG(int, robots, 3, "robots, each driving its own stretch");
ABSL_FLAG(int, stretch_length, 300, "frames per robot stretch");
ABSL_FLAG(std::string, results_md, "",
          "also write the results table as Markdown to this file");
ABSL_FLAG(std::string, encoder, "hog-64x32-c8-s8-b6",
          "image code (see fleetmem-encoder-eval for the variants)");
ABSL_FLAG(int, upload_batch, 50, "traces per upload call");
ABSL_FLAG(int, replay_count, 100, "traces each robot samples for replay");

namespace fleetmem::demo {
namespace {

using Clock = std::chrono::steady_clock;

// Correct match: within +-2 files of the query (README.md).
constexpr double kToleranceUnits = 2.0 * kNordlandUnitsPerFile;
// Matches per query: enough for WR (recall@1..6).
constexpr uint32_t kQueryK = 6;
constexpr char kAttribution[] =
    "Data: Nordland railway, summer and winter (NRK, Nordlandsbanen footage, "
    "Creative Commons Attribution; trimmed copy from TimQuelch/seqslam).";

double MillisSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start)
      .count();
}

// Progress lines from several threads, one whole line at a time.
class Progress {
 public:
  template <typename... Args>
  void Line(const absl::FormatSpec<Args...>& format, const Args&... args) {
    const std::string line = absl::StrFormat(format, args...);
    std::lock_guard<std::mutex> lock(mu_);
    std::printf("%s\n", line.c_str());
    std::fflush(stdout);
  }

 private:
  std::mutex mu_;
};

struct Setup {
  std::string fleet_id;
  std::string summer_dir;
  std::string winter_dir;
  std::vector<int> numbers;  // frame numbers, the same in both seasons
  const ImageEncoder* encoder = nullptr;
  size_t upload_batch = 50;
};

// What one robot did: its traces, its winter query codes and its upload
// timings.
struct Drive {
  std::string robot_id;
  Stretch stretch;
  std::unique_ptr<client::Client> client;
  std::vector<v1::MemoryTrace> traces;           // uploaded, summer
  std::vector<std::vector<float>> winter_codes;  // same places, winter
  std::vector<double> winter_x;
  uint64_t consolidations = 0;          // triggered by this robot's uploads
  std::vector<double> upload_ms_plain;  // calls without consolidation
  std::vector<double> upload_ms_consolidating;  // calls that consolidated
  absl::Status status;
};

absl::StatusOr<std::vector<float>> EncodeFrame(const Setup& setup,
                                               const std::string& dir,
                                               int number, cv::Mat* image) {
  absl::StatusOr<cv::Mat> grey = LoadNordlandGrey(dir, number);
  if (!grey.ok()) return grey.status();
  if (image != nullptr) *image = *grey;
  return setup.encoder->Encode(*grey);
}

// Step 1 for one robot: encode its stretch, compute rewards, upload.
absl::Status DriveStretch(const Setup& setup, Drive& drive,
                          Progress& progress) {
  std::mt19937_64 rng(std::hash<std::string>{}(drive.robot_id));
  std::vector<std::vector<float>> codes;
  std::vector<double> x;
  std::vector<float> internal;
  for (size_t i = drive.stretch.begin; i < drive.stretch.end; ++i) {
    cv::Mat image;
    absl::StatusOr<std::vector<float>> code =
        EncodeFrame(setup, setup.summer_dir, setup.numbers[i], &image);
    if (!code.ok()) return code.status();
    absl::StatusOr<cv::Mat> moved =
        RandomShiftCrop(image, ShiftCropOptions{}, rng);
    if (!moved.ok()) return moved.status();
    absl::StatusOr<std::vector<float>> moved_code =
        setup.encoder->Encode(*moved);
    if (!moved_code.ok()) return moved_code.status();
    internal.push_back(InternalReward(*code, *moved_code));
    codes.push_back(*std::move(code));
    x.push_back(setup.numbers[i]);

    absl::StatusOr<std::vector<float>> winter =
        EncodeFrame(setup, setup.winter_dir, setup.numbers[i], nullptr);
    if (!winter.ok()) return winter.status();
    drive.winter_codes.push_back(*std::move(winter));
    drive.winter_x.push_back(setup.numbers[i]);
  }
  // Rewards (rewards.h): R_in = 1 - cos(E(q), E(A(q))) with A a random crop
  // of up to 4 px sideways and 2 px vertically, resized back; R_ex = triplet
  // loss on this robot's own stretch, positive = the harder adjacent frame
  // (+-1 file), negative = the nearest code more than 10 files away, margin
  // 0.1. Both come from the robot's own data only, as on a real robot.
  const std::vector<float> external =
      ExternalRewards(codes, x, TripletOptions{});

  const int64_t now_ns = absl::ToUnixNanos(absl::Now());
  for (size_t k = 0; k < codes.size(); ++k) {
    v1::MemoryTrace& trace = drive.traces.emplace_back();
    trace.set_robot_id(drive.robot_id);
    trace.set_seq(k + 1);
    trace.set_domain("summer");
    trace.mutable_code()->Assign(codes[k].begin(), codes[k].end());
    trace.mutable_pose()->set_x(x[k]);
    trace.set_reward_external(external[k]);
    trace.set_reward_internal(internal[k]);
    trace.set_reward(external[k] + internal[k]);
    // One frame per second of driving, for a plausible timeline.
    trace.set_timestamp_ns(now_ns + static_cast<int64_t>(k) * 1'000'000'000);
    trace.set_encoder_version(setup.encoder->version());
  }
  progress.Line(
      "[%s] encoded frames %d..%d (%zu traces, mean R_ex %.3f, "
      "mean R_in %.3f)",
      drive.robot_id, setup.numbers[drive.stretch.begin],
      setup.numbers[drive.stretch.end - 1], drive.traces.size(),
      std::accumulate(external.begin(), external.end(), 0.0) / external.size(),
      std::accumulate(internal.begin(), internal.end(), 0.0) / internal.size());

  const std::span<const v1::MemoryTrace> all(drive.traces);
  for (size_t done = 0; done < all.size();) {
    const size_t n = std::min(setup.upload_batch, all.size() - done);
    const auto start = Clock::now();
    absl::StatusOr<v1::UploadTracesResponse> response =
        drive.client->Upload(setup.fleet_id, all.subspan(done, n));
    const double ms = MillisSince(start);
    if (!response.ok()) {
      return absl::Status(response.status().code(),
                          absl::StrCat(drive.robot_id, " upload: ",
                                       response.status().message()));
    }
    done += n;
    drive.consolidations += response->consolidations();
    (response->consolidations() > 0 ? drive.upload_ms_consolidating
                                    : drive.upload_ms_plain)
        .push_back(ms);
    progress.Line(
        "[%s] uploaded %zu/%zu traces (accepted %d, duplicates %d, "
        "consolidations %d) in %.1f ms",
        drive.robot_id, done, all.size(), response->accepted(),
        response->duplicates(), response->consolidations(), ms);
  }
  return absl::OkStatus();
}

double Mean(const std::vector<double>& values) {
  if (values.empty()) return 0.0;
  return std::accumulate(values.begin(), values.end(), 0.0) / values.size();
}

// One row of the results table.
struct Row {
  std::string system;
  core::FirstCorrectRanks ranks;
  std::string traces;
  std::string clusters;
  std::string consolidation_ms;
  double query_ms = 0.0;
};

std::string Table(const std::vector<Row>& rows) {
  std::string out =
      "| system | recall@1 | recall@5 | WR | traces held | clusters held | "
      "time per consolidation (ms) | time per query (ms) |\n"
      "|---|---:|---:|---:|---:|---:|---:|---:|\n";
  for (const Row& row : rows) {
    absl::StrAppendFormat(
        &out, "| %s | %.3f | %.3f | %.3f | %s | %s | %s | %.3f |\n", row.system,
        core::RecallAtK(row.ranks, 1), core::RecallAtK(row.ranks, 5),
        core::WeightedRecall(row.ranks), row.traces, row.clusters,
        row.consolidation_ms, row.query_ms);
  }
  return out;
}

// Live clusters of the fleet from its event history: id -> (traces, mean
// reward), and how many were added and forgotten.
struct EventSummary {
  std::map<uint64_t, std::pair<uint32_t, float>> live;
  uint64_t added = 0;
  uint64_t forgotten = 0;

  double MeanReward() const {
    double sum = 0.0, count = 0.0;
    for (const auto& [id, cluster] : live) {
      sum += cluster.first * static_cast<double>(cluster.second);
      count += cluster.first;
    }
    return count > 0.0 ? sum / count : 0.0;
  }
};

absl::StatusOr<EventSummary> ReadEvents(client::Client& client,
                                        const std::string& fleet_id,
                                        uint64_t last_event_id) {
  EventSummary summary;
  if (last_event_id == 0) return summary;
  absl::StatusOr<uint64_t> last =
      client.Watch(fleet_id, 0, [&](const v1::MemoryEvent& event) {
        if (event.type() == v1::MemoryEvent::CLUSTER_ADDED) {
          ++summary.added;
          summary.live[event.cluster_id()] = {event.trace_count(),
                                              event.mean_reward()};
        } else if (event.type() == v1::MemoryEvent::CLUSTER_FORGOTTEN) {
          ++summary.forgotten;
          summary.live.erase(event.cluster_id());
        }
        return event.id() < last_event_id;
      });
  if (!last.ok()) return last.status();
  return summary;
}

absl::Status Run() {
  // Setup: data, encoder, stretches, fleet id. ------------------------------
  Setup setup;
  setup.fleet_id = absl::GetFlag(FLAGS_fleet);
  if (setup.fleet_id.empty()) {
    setup.fleet_id = absl::StrCat(
        "nordland-demo-",
        absl::FormatTime("%Y%m%d-%H%M%S", absl::Now(), absl::UTCTimeZone()));
  }
  const std::string root = absl::GetFlag(FLAGS_data) + "/nordland";
  setup.summer_dir = root + "/summer";
  setup.winter_dir = root + "/winter";
  absl::StatusOr<std::vector<int>> summer =
      ListNordlandFrames(setup.summer_dir);
  if (!summer.ok()) return summer.status();
  absl::StatusOr<std::vector<int>> winter =
      ListNordlandFrames(setup.winter_dir);
  if (!winter.ok()) return winter.status();
  if (*summer != *winter) {
    return absl::FailedPreconditionError(
        absl::StrCat(setup.summer_dir, " and ", setup.winter_dir,
                     " do not hold the same frames"));
  }
  setup.numbers = *std::move(summer);
  absl::StatusOr<std::unique_ptr<ImageEncoder>> encoder =
      NewEncoderByName(absl::GetFlag(FLAGS_encoder));
  if (!encoder.ok()) return encoder.status();
  setup.encoder = encoder->get();
  if (absl::GetFlag(FLAGS_upload_batch) < 1) {
    return absl::InvalidArgumentError("--upload_batch must be >= 1");
  }
  setup.upload_batch = absl::GetFlag(FLAGS_upload_batch);
  absl::StatusOr<std::vector<Stretch>> stretches =
      SpreadStretches(setup.numbers.size(), absl::GetFlag(FLAGS_robots),
                      absl::GetFlag(FLAGS_stretch_length));
  if (!stretches.ok()) return stretches.status();

  client::ClientOptions client_options;
  client_options.target = absl::GetFlag(FLAGS_server);
  std::vector<Drive> drives(stretches->size());
  for (size_t r = 0; r < drives.size(); ++r) {
    drives[r].robot_id = absl::StrCat("robot-", r + 1);
    drives[r].stretch = (*stretches)[r];
    drives[r].client = client::Client::Create(client_options);
  }
  Progress progress;
  progress.Line(
      "fleetmem demo: fleet %s on %s, %zu robots x %d summer "
      "frames, encoder %s (%zu dims), data %s",
      setup.fleet_id, client_options.target, drives.size(),
      absl::GetFlag(FLAGS_stretch_length), setup.encoder->version(),
      setup.encoder->dimension(), root);

  // 1. The robots drive and upload in parallel. ------------------------------
  {
    std::vector<std::thread> threads;
    for (Drive& drive : drives) {
      threads.emplace_back([&setup, &drive, &progress] {
        drive.status = DriveStretch(setup, drive, progress);
      });
    }
    for (std::thread& thread : threads) thread.join();
  }
  for (const Drive& drive : drives) {
    if (!drive.status.ok()) return drive.status;
  }

  // 2. Consolidate the rest, then look at the memory. ------------------------
  client::Client& observer = *drives.front().client;
  absl::StatusOr<v1::GetStatsResponse> before =
      observer.GetStats(setup.fleet_id);
  if (!before.ok()) return before.status();
  const auto consolidate_start = Clock::now();
  absl::StatusOr<v1::ConsolidateResponse> consolidated =
      observer.Consolidate(setup.fleet_id);
  const double consolidate_ms = MillisSince(consolidate_start);
  if (!consolidated.ok()) return consolidated.status();
  progress.Line(
      "consolidate: %d pending traces -> %d clusters added, %d "
      "traces downsampled, %d clusters forgotten; memory now %d "
      "clusters, %d traces (%.1f ms)",
      consolidated->consolidated_traces(), consolidated->clusters_added(),
      consolidated->downsampled_traces(), consolidated->clusters_forgotten(),
      consolidated->clusters(), consolidated->traces(), consolidate_ms);
  absl::StatusOr<v1::GetStatsResponse> stats =
      observer.GetStats(setup.fleet_id);
  if (!stats.ok()) return stats.status();
  // The call consolidated one batch per robot with pending traces.
  const uint64_t final_batches =
      stats->consolidations() - before->consolidations();
  progress.Line(
      "stats: %d consolidations, %d clusters forgotten in all, "
      "K_max %d, N_max %d, %d pending",
      stats->consolidations(), stats->clusters_forgotten(),
      stats->max_clusters(), stats->max_traces_per_cluster(),
      stats->pending_traces());
  for (const v1::RobotStats& robot : stats->robots()) {
    progress.Line("stats: %s holds %d of its %d uploaded traces",
                  robot.robot_id(), robot.traces(), robot.received());
  }
  if (stats->consolidations() == 0 || stats->clusters_forgotten() == 0) {
    progress.Line(
        "note: this run did not both consolidate and forget; use "
        "more robots or longer stretches to exercise the bounds");
  }
  absl::StatusOr<EventSummary> events =
      ReadEvents(observer, setup.fleet_id, stats->last_event_id());
  if (!events.ok()) return events.status();
  double uploaded_reward = 0.0;
  size_t uploaded = 0;
  for (const Drive& drive : drives) {
    for (const v1::MemoryTrace& trace : drive.traces) {
      uploaded_reward += trace.reward();
      ++uploaded;
    }
  }
  uploaded_reward /= std::max<size_t>(uploaded, 1);
  progress.Line(
      "events: %d clusters added, %d forgotten; mean reward of the "
      "traces held %.3f vs %.3f over all uploaded",
      events->added, events->forgotten, events->MeanReward(), uploaded_reward);

  // Fleet sharing: each robot refreshes its dynamic memory from everyone's.
  const uint32_t replay_count = std::max(1, absl::GetFlag(FLAGS_replay_count));
  for (Drive& drive : drives) {
    absl::StatusOr<std::vector<v1::MemoryTrace>> sampled =
        drive.client->SampleReplay(setup.fleet_id, drive.robot_id,
                                   replay_count);
    if (!sampled.ok()) return sampled.status();
    std::map<std::string, int> by_robot;
    double reward = 0.0;
    for (const v1::MemoryTrace& trace : *sampled) {
      ++by_robot[trace.robot_id()];
      reward += trace.reward();
    }
    std::vector<std::string> parts;
    for (const auto& [robot, count] : by_robot) {
      parts.push_back(absl::StrCat(robot, " ", count));
    }
    progress.Line(
        "replay: %s sampled %zu traces from {%s}; mean reward %.3f "
        "(memory %.3f)",
        drive.robot_id, sampled->size(), absl::StrJoin(parts, ", "),
        sampled->empty() ? 0.0 : reward / sampled->size(),
        events->MeanReward());
  }

  // 3. Winter queries: fleet memory vs all traces by brute force. -----------
  Row memory_row, baseline_row;
  memory_row.system = "fleet memory (server)";
  baseline_row.system = "all traces, no memory bound (baseline)";
  BruteForceIndex baseline(setup.encoder->dimension());
  for (const Drive& drive : drives) {
    for (const v1::MemoryTrace& trace : drive.traces) {
      baseline.Add(
          std::span<const float>(trace.code().data(), trace.code().size()),
          trace.pose().x());
    }
  }
  std::vector<double> server_ms, local_ms;
  size_t covered = 0;
  for (Drive& drive : drives) {
    for (size_t q = 0; q < drive.winter_codes.size(); ++q) {
      const std::vector<float>& code = drive.winter_codes[q];
      const double x = drive.winter_x[q];
      v1::QueryPlaceRequest request;
      request.set_fleet_id(setup.fleet_id);
      request.mutable_code()->Assign(code.begin(), code.end());
      request.set_k(kQueryK);
      auto start = Clock::now();
      absl::StatusOr<std::vector<v1::PlaceMatch>> matches =
          drive.client->QueryPlace(request);
      server_ms.push_back(MillisSince(start));
      if (!matches.ok()) return matches.status();
      std::vector<double> found;
      for (const v1::PlaceMatch& match : *matches) {
        found.push_back(match.trace().pose().x());
      }
      memory_row.ranks.push_back(FirstCorrectRank(found, x, kToleranceUnits));

      start = Clock::now();
      found = baseline.Search(code, kQueryK);
      local_ms.push_back(MillisSince(start));
      baseline_row.ranks.push_back(FirstCorrectRank(found, x, kToleranceUnits));

      // Does the memory still hold the place at all (after forgetting)?
      v1::QueryPlaceRequest near = request;
      near.set_k(1);
      near.mutable_near()->set_x(x);
      near.set_radius_m(kToleranceUnits);
      absl::StatusOr<std::vector<v1::PlaceMatch>> held =
          drive.client->QueryPlace(near);
      if (!held.ok()) return held.status();
      covered += held->empty() ? 0 : 1;
    }
    progress.Line("[%s] queried %zu winter frames", drive.robot_id,
                  drive.winter_codes.size());
  }
  const size_t queries = memory_row.ranks.size();
  memory_row.traces = absl::StrCat(stats->traces());
  memory_row.clusters = absl::StrCat(stats->clusters());
  memory_row.query_ms = Mean(server_ms);
  baseline_row.traces = absl::StrCat(baseline.size());
  baseline_row.clusters = "-";
  baseline_row.consolidation_ms = "-";
  baseline_row.query_ms = Mean(local_ms);

  std::vector<double> plain, consolidating;
  uint64_t auto_consolidations = 0;
  for (const Drive& drive : drives) {
    plain.insert(plain.end(), drive.upload_ms_plain.begin(),
                 drive.upload_ms_plain.end());
    consolidating.insert(consolidating.end(),
                         drive.upload_ms_consolidating.begin(),
                         drive.upload_ms_consolidating.end());
    auto_consolidations += drive.consolidations;
  }
  // Time per consolidation: the final Consolidate call per batch it took;
  // if it had nothing to do (stretches a multiple of the segment size), the
  // extra time of the upload calls that consolidated, marked as an estimate.
  std::string consolidation_timing;
  if (final_batches > 0) {
    memory_row.consolidation_ms =
        absl::StrFormat("%.1f", consolidate_ms / final_batches);
    consolidation_timing = absl::StrFormat(
        "the final Consolidate call (client round trip, %.1f ms) divided by "
        "the %d batches it consolidated (%d traces), including forgetting %d "
        "clusters",
        consolidate_ms, final_batches, consolidated->consolidated_traces(),
        consolidated->clusters_forgotten());
  } else if (!consolidating.empty() && !plain.empty()) {
    memory_row.consolidation_ms =
        absl::StrFormat("~%.1f", Mean(consolidating) - Mean(plain));
    consolidation_timing =
        "estimated (~) as the mean round trip of the upload calls that "
        "triggered a consolidation minus that of the others (the final "
        "Consolidate call had nothing left to do)";
  } else {
    memory_row.consolidation_ms = "-";
    consolidation_timing = "not measured (no consolidation was timed)";
  }
  const std::string table = Table({memory_row, baseline_row});
  const std::string notes = absl::StrFormat(
      "- %zu winter queries (the summer stretches of %zu robots, frames "
      "%s); correct if a match is within +-2 files (+-%.0f units).\n"
      "- Encoder %s (%zu dims). Memory bounds of the fleet: N_max = %d "
      "traces per cluster, K_max = %d clusters; %d consolidations (one batch "
      "of one robot each, %d of them triggered by uploads), %d clusters "
      "forgotten.\n"
      "- Time per consolidation: %s. Upload calls that triggered a "
      "consolidation took %.1f ms on average vs %.1f ms for the others.\n"
      "- Time per query: fleet memory = QueryPlace round trip (k = %d, "
      "sequential); baseline = in-process brute force over %zu codes.\n"
      "- The memory still holds a trace within +-2 files of %zu of %zu "
      "query places (%.1f%%): an upper bound of its recall.\n",
      queries, drives.size(),
      absl::StrJoin(drives, ", ",
                    [&](std::string* out, const Drive& drive) {
                      absl::StrAppend(out, setup.numbers[drive.stretch.begin],
                                      "..",
                                      setup.numbers[drive.stretch.end - 1]);
                    }),
      kToleranceUnits, setup.encoder->version(), setup.encoder->dimension(),
      stats->max_traces_per_cluster(), stats->max_clusters(),
      stats->consolidations(), auto_consolidations, stats->clusters_forgotten(),
      consolidation_timing, Mean(consolidating), Mean(plain), kQueryK,
      baseline.size(), covered, queries,
      100.0 * covered / std::max<size_t>(queries, 1));

  std::printf("\nResults (fleet %s)\n\n%s\n%s\n%s\n", setup.fleet_id.c_str(),
              table.c_str(), notes.c_str(), kAttribution);
  const std::string md_path = absl::GetFlag(FLAGS_results_md);
  if (!md_path.empty()) {
    std::ofstream md(md_path);
    md << "# fleetmem demo: Nordland summer -> winter, fleet of "
       << drives.size() << " robots\n\n"
       << table << "\n"
       << notes << "\n"
       << kAttribution << "\n";
    if (!md) return absl::InternalError(absl::StrCat("cannot write ", md_path));
    std::printf("Results table written to %s\n", md_path.c_str());
  }
  return absl::OkStatus();
}

}  // namespace
}  // namespace fleetmem::demo

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "Fleet memory demo on Nordland: three robots share one memory of the "
      "summer route and recognise its places in winter.");
  fleetmem::demo::ParseDashedCommandLine(argc, argv);
  const absl::Status status = fleetmem::demo::Run();
  if (!status.ok()) {
    std::cerr << "fleetmem-demo: " << status << "\n";
    return 1;
  }
  return 0;
}
