// fleetmem-demo: a fleet of real fleetmem-robot processes builds one shared
// memory from the real Nordland summer images, then the same robots
// recognise those places in winter.
//
//   1. Summer: one fleetmem-robot process per robot drives its own stretch
//      of the summer route (encode, rewards, relocalise, store-and-forward
//      upload, refresh of its dynamic memory). The server consolidates each
//      robot segment of 200 traces as it arrives and forgets clusters beyond
//      K_max.
//   2. A final Consolidate (timed) takes the rest; stats and the event
//      history describe the memory.
//   3. Winter: the same robots drive the same stretches in winter, query
//      only: each relocalises every frame against the fleet memory (k = 6)
//      and, per segment, replays from a dynamic memory refreshed from the
//      whole fleet (its peers' summer places included).
//   4. The table: recall@1/5 and WR of the winter relocalisations against
//      the fleet memory, against exact search over every summer code
//      (computed here, the unbounded baseline); per robot, what it uploaded,
//      replayed from its peers and relocalised.
//
//   fleetmem-demo [--server HOST:PORT] [--data DIR] [--fleet ID]
//                 [--robots N] [--stretch-length N] [--results-md FILE]
//                 [--work-dir DIR] [--robot-binary PATH]
//                 [--sequential-robots]
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <numeric>
#include <set>
#include <span>
#include <sstream>
#include <string>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/metric_head.h"
#include "clients/robot/memory/robot_store.h"
#include "clients/robot/sensing/code_search.h"
#include "clients/robot/sensing/image_encoder.h"
#include "clients/robot/sensing/nordland.h"
#include "clients/robot/sensing/sequence_search.h"
#include "fleetmem_paths.h"
#include "fleetmem_version.h"
#include "google/protobuf/util/json_util.h"
#include "services/common/cli_program.h"
#include "services/common/files.h"
#include "services/core/place_metrics.h"

namespace fleetmem::demo {
namespace {

// The command line (CLI11; --name-with-dashes or --name_with_underscores).
struct DemoFlags {
  std::string server = "127.0.0.1:50051";
  std::string data = FLEETMEM_DATA_DIR;
  std::string fleet;
  int robots = 3;
  int stretch_length = 300;
  std::string results_md;
  std::string encoder = "hog-64x32-c8-s8-b6";
  int segment_size = 200;
  std::string work_dir = ".demo/robots";
  std::string robot_binary;
  std::string gpl_model;
  int learn_steps = 30;
  bool learn = true;
  bool sequential_robots = false;
  int sequence = 10;
};

DemoFlags& Flags() {
  static DemoFlags* flags = new DemoFlags;
  return *flags;
}

}  // namespace
}  // namespace fleetmem::demo

namespace fleetmem::demo {
namespace {

using Clock = std::chrono::steady_clock;
using robot::state::RobotStatus;

// Correct match: within +-2 files of the query (README.md).
constexpr double kToleranceUnits = 2.0 * robot::kNordlandUnitsPerFile;
// Matches per query: enough for WR (recall@1..6).
constexpr uint32_t kQueryK = 6;
// Matches per frame for the sequence search (fleetmem-robot's
// --sequence-candidates default), and the lengths whose WR the notes list.
constexpr uint32_t kSequenceCandidates = 20;
constexpr size_t kSequenceLengths[] = {1, 3, 5, 10, 20};
constexpr char kAttribution[] =
    "Data: Nordland railway, summer and winter (NRK, Nordlandsbanen footage, "
    "Creative Commons Attribution; trimmed copy from TimQuelch/seqslam).";

double MillisSince(Clock::time_point start) {
  return std::chrono::duration<double, std::milli>(Clock::now() - start)
      .count();
}

struct Setup {
  std::string fleet_id;
  std::string server;
  std::string summer_dir;
  std::string winter_dir;
  std::string robot_binary;
  std::string work_dir;
  std::vector<int> numbers;  // frame numbers, the same in both seasons
  std::unique_ptr<robot::ImageEncoder> encoder;
  std::string encoder_name;
  int segment_size = 200;
  // The robots learn the metric head on the fleet code (--learn).
  bool learn_metric = false;
  // Non-empty: the robots run the GPL model and learn.
  std::string gpl_model;
};

// `classical`'s setup for a fleet of its own, `suffix` on its id and work
// dir (no encoder: the learning passes encode with the classical one).
Setup LearningSetup(const Setup& classical, const std::string& suffix) {
  Setup setup;
  setup.fleet_id = classical.fleet_id + suffix;
  setup.server = classical.server;
  setup.summer_dir = classical.summer_dir;
  setup.winter_dir = classical.winter_dir;
  setup.robot_binary = classical.robot_binary;
  setup.work_dir = classical.work_dir + suffix;
  setup.numbers = classical.numbers;
  setup.encoder_name = classical.encoder_name;
  setup.segment_size = classical.segment_size;
  return setup;
}

struct Drive {
  std::string robot_id;
  robot::Stretch stretch;
  RobotStatus summer;
  RobotStatus winter;
};

std::string StatusPath(const Setup& setup, const Drive& drive,
                       const std::string& season) {
  return absl::StrCat(setup.work_dir, "/", drive.robot_id, "-", season,
                      "/status.json");
}

// Runs one fleetmem-robot per drive over `season` and waits for all; their
// progress goes to this program's stderr.
absl::Status RunRobots(const Setup& setup, std::vector<Drive>& drives,
                       const std::string& season, bool query_only) {
  const bool sequential = Flags().sequential_robots;
  std::vector<pid_t> pids;
  std::vector<int> exit_statuses(drives.size(), 0);
  for (const Drive& drive : drives) {
    const std::string dir =
        absl::StrCat(setup.work_dir, "/", drive.robot_id, "-", season);
    std::vector<std::string> args = {
        setup.robot_binary,
        "--server",
        setup.server,
        "--fleet",
        setup.fleet_id,
        "--robot-id",
        drive.robot_id,
        "--source",
        absl::StrCat("nordland:",
                     season == "summer" ? setup.summer_dir : setup.winter_dir),
        "--data-dir",
        dir,
        "--first",
        absl::StrCat(drive.stretch.begin),
        "--last",
        absl::StrCat(drive.stretch.end),
        "--segment-size",
        absl::StrCat(setup.segment_size)};
    if (setup.gpl_model.empty()) {
      args.insert(args.end(), {"--encoder", setup.encoder_name});
      if (setup.learn_metric) args.push_back("--learn");
    } else {
      args.insert(args.end(),
                  {"--gpl-model", setup.gpl_model, "--learn", "--learn-steps",
                   absl::StrCat(Flags().learn_steps)});
    }
    if (query_only) args.push_back("--query-only");
    args.insert(args.end(), {"--sequence", absl::StrCat(Flags().sequence)});
    std::vector<char*> argv;
    for (std::string& arg : args) argv.push_back(arg.data());
    argv.push_back(nullptr);
    pid_t pid = 0;
    const int error = posix_spawn(&pid, setup.robot_binary.c_str(), nullptr,
                                  nullptr, argv.data(), environ);
    if (error != 0) {
      return absl::InternalError(absl::StrCat(
          "cannot start ", setup.robot_binary, ": ", std::strerror(error)));
    }
    std::printf("demo: started fleetmem-robot %s (%s, frames %d..%d, pid %d)\n",
                drive.robot_id.c_str(), season.c_str(),
                setup.numbers[drive.stretch.begin],
                setup.numbers[drive.stretch.end - 1], pid);
    std::fflush(stdout);
    pids.push_back(pid);
    if (sequential) waitpid(pid, &exit_statuses[pids.size() - 1], 0);
  }
  absl::Status result;
  for (size_t i = 0; i < pids.size(); ++i) {
    int& status = exit_statuses[i];
    if (!sequential) waitpid(pids[i], &status, 0);
    if (!WIFEXITED(status) || WEXITSTATUS(status) != 0) {
      result.Update(absl::InternalError(absl::StrCat(
          "fleetmem-robot ", drives[i].robot_id, " (", season,
          ") failed with status ", status, "; see its lines above")));
    }
  }
  if (!result.ok()) return result;
  for (Drive& drive : drives) {
    const std::string path = StatusPath(setup, drive, season);
    absl::StatusOr<std::string> json = files::ReadFile(path);
    RobotStatus& status = season == "summer" ? drive.summer : drive.winter;
    if (!json.ok() ||
        !google::protobuf::util::JsonStringToMessage(*json, &status).ok()) {
      return absl::InternalError(absl::StrCat("cannot read ", path));
    }
  }
  return absl::OkStatus();
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
        } else if (event.type() == v1::MemoryEvent::CLUSTER_MERGED) {
          // The survivor's mean reward is kept as it was (events do not
          // say which traces the merge dropped).
          ++summary.forgotten;
          auto from = summary.live.find(event.cluster_id());
          auto into = summary.live.find(event.merged_into());
          if (from != summary.live.end() && into != summary.live.end()) {
            const uint32_t both = from->second.first + into->second.first;
            into->second.first = both - std::min(both, event.traces_dropped());
          }
          summary.live.erase(event.cluster_id());
        }
        return event.id() < last_event_id;
      });
  if (!last.ok()) return last.status();
  return summary;
}

struct Row {
  std::string system;
  core::FirstCorrectRanks ranks;
  std::string traces;
  std::string clusters;
  std::string consolidation_ms;
  double query_ms = 0.0;
};

// A learned model's row, scored on the baseline's map of `map_size` summer
// frames (no clusters, no consolidation).
Row MapRow(std::string system, size_t map_size) {
  Row row;
  row.system = std::move(system);
  row.traces = absl::StrCat(map_size);
  row.clusters = "-";
  row.consolidation_ms = "-";
  return row;
}

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

std::string RobotTable(const Setup& setup, const std::vector<Drive>& drives) {
  std::string out =
      "| robot | frames | summer traces uploaded | dynamic memory after "
      "winter (own / peers) | peer traces brought by refreshes | traces "
      "replayed from peers (winter) | winter relocalisation recall@1 | "
      "winter relocalisation WR |\n"
      "|---|---|---:|---:|---:|---:|---:|---:|\n";
  for (const Drive& drive : drives) {
    uint64_t own = 0, peers = 0;
    for (const auto& [robot_id, count] :
         drive.winter.dynamic_memory_by_robot()) {
      (robot_id == drive.robot_id ? own : peers) += count;
    }
    const core::FirstCorrectRanks ranks =
        robot::RelocalisationRanks(drive.winter.counters());
    absl::StrAppendFormat(
        &out, "| %s | %d..%d | %d | %d / %d | %d | %d | %.3f | %.3f |\n",
        drive.robot_id, setup.numbers[drive.stretch.begin],
        setup.numbers[drive.stretch.end - 1],
        drive.summer.counters().traces_uploaded(), own, peers,
        drive.winter.counters().refreshed_peer_traces(),
        drive.winter.counters().replayed_peer(), core::RecallAtK(ranks, 1),
        core::WeightedRecall(ranks));
  }
  return out;
}

absl::StatusOr<std::vector<float>> EncodeFrame(const Setup& setup,
                                               const std::string& dir,
                                               int number) {
  absl::StatusOr<cv::Mat> grey = robot::LoadNordlandGrey(dir, number);
  if (!grey.ok()) return grey.status();
  return setup.encoder->EncodeImage(*grey);
}

// Runs `drives` again in the fleet of `setup`, whose robots learn: summer
// uploads, a Consolidate, then winter query-only (each winter segment is
// paired with the summer traces in the robot's dynamic memory, refreshed
// from the whole fleet).
absl::Status RunLearningFleet(const Setup& setup, std::vector<Drive>& drives,
                              client::Client& observer) {
  absl::Status ran = RunRobots(setup, drives, "summer", /*query_only=*/false);
  if (!ran.ok()) return ran;
  absl::StatusOr<v1::ConsolidateResponse> consolidated =
      observer.Consolidate(setup.fleet_id);
  if (!consolidated.ok()) return consolidated.status();
  return RunRobots(setup, drives, "winter", /*query_only=*/true);
}

// Codes of every frame of the drives' stretches in both seasons, and where
// each frame is.
struct SeasonCodes {
  std::vector<std::vector<float>> summer, winter;
  std::vector<double> summer_x, winter_x;
  std::vector<size_t> owner;  // drive of each winter frame
};

absl::StatusOr<SeasonCodes> CodesOf(
    const Setup& setup, const std::vector<Drive>& drives,
    const std::function<absl::StatusOr<std::vector<float>>(const cv::Mat&)>&
        encode) {
  SeasonCodes codes;
  for (size_t d = 0; d < drives.size(); ++d) {
    for (size_t i = drives[d].stretch.begin; i < drives[d].stretch.end; ++i) {
      for (const bool winter : {false, true}) {
        absl::StatusOr<cv::Mat> grey = robot::LoadNordlandGrey(
            winter ? setup.winter_dir : setup.summer_dir, setup.numbers[i]);
        if (!grey.ok()) return grey.status();
        absl::StatusOr<std::vector<float>> z = encode(*grey);
        if (!z.ok()) return z.status();
        (winter ? codes.winter : codes.summer).push_back(*std::move(z));
        (winter ? codes.winter_x : codes.summer_x).push_back(setup.numbers[i]);
      }
      codes.owner.push_back(d);
    }
  }
  return codes;
}

// Scores winter queries in driving order: each query's rank among its
// first kQueryK matches (single frame) and, for every length of
// kSequenceLengths and --sequence, among them re-ranked over the last
// frames (sequence_search.h; the distance travelled between Nordland files
// is their spacing). Restart() at the start of each drive.
class QueryScorer {
 public:
  QueryScorer()
      : lengths_(std::begin(kSequenceLengths), std::end(kSequenceLengths)),
        window_(std::max<size_t>(Flags().sequence, 20)) {
    lengths_.insert(Flags().sequence);
  }
  void Restart() { window_.Clear(); }
  void Score(std::span<const robot::BruteForceIndex::Neighbour> found,
             double x) {
    std::vector<robot::SequenceCandidate> candidates;
    for (const auto& neighbour : found) {
      candidates.push_back(
          {.place = {.x = neighbour.label}, .distance = neighbour.distance});
    }
    window_.Add({.x = x}, candidates);
    for (size_t length : lengths_) {
      const std::vector<core::Place> places = robot::SequencePlaces(
          window_.frames(), {.length = length, .tolerance = kToleranceUnits},
          kQueryK);
      ranks_[length].push_back(
          robot::FirstCorrectRank(places, {.x = x}, kToleranceUnits));
    }
  }
  const core::FirstCorrectRanks& Single() { return ranks_[1]; }
  const core::FirstCorrectRanks& Sequence() { return ranks_[Flags().sequence]; }
  // "WR 0.412 (1), 0.455 (3), ..." over kSequenceLengths.
  std::string ByLength() {
    std::vector<std::string> parts;
    for (size_t length : kSequenceLengths) {
      parts.push_back(absl::StrFormat(
          "%.3f (%d)", core::WeightedRecall(ranks_[length]), length));
    }
    return absl::StrJoin(parts, ", ");
  }

 private:
  std::set<size_t> lengths_;
  robot::SequenceWindow window_;
  std::map<size_t, core::FirstCorrectRanks> ranks_;
};

using DescribeFn =
    std::function<absl::StatusOr<std::vector<std::vector<float>>>(
        std::span<const std::vector<float>>)>;

// Which drives' winter frames ScoreWinter takes as queries.
enum class Queries { kAll, kOwn, kPeers };

// Scores the winter frames of drive `drive` (kOwn), of every other drive
// (kPeers) or of all (kAll) against every summer
// frame of the stretches, both described by `describe`, like the baseline
// row. Time per query: the winter code's descriptor plus the brute-force
// search (the map's descriptors are made once).
absl::Status ScoreWinter(const DescribeFn& describe, const SeasonCodes& codes,
                         Queries queries, size_t drive, QueryScorer& scorer,
                         double& ms) {
  absl::StatusOr<std::vector<std::vector<float>>> map = describe(codes.summer);
  if (!map.ok()) return map.status();
  if (map->empty()) return absl::OkStatus();
  robot::BruteForceIndex index(map->front().size());
  for (size_t j = 0; j < map->size(); ++j) {
    index.Add((*map)[j], codes.summer_x[j]);
  }
  for (size_t j = 0; j < codes.winter.size(); ++j) {
    if ((queries == Queries::kOwn && codes.owner[j] != drive) ||
        (queries == Queries::kPeers && codes.owner[j] == drive)) {
      continue;
    }
    if (j == 0 || codes.owner[j] != codes.owner[j - 1]) scorer.Restart();
    const auto start = Clock::now();
    absl::StatusOr<std::vector<std::vector<float>>> q =
        describe(std::span<const std::vector<float>>(&codes.winter[j], 1));
    if (!q.ok()) return q.status();
    const auto found = index.SearchScored((*q)[0], kSequenceCandidates);
    ms += MillisSince(start);
    scorer.Score(found, codes.winter_x[j]);
  }
  return absl::OkStatus();
}

// The learning pass (default learner): the same drives in a fleet of their
// own whose robots learn the metric head on the fleet code. Rows: each
// robot's head after its winter drive, scored on the baseline's map (every
// summer frame of the stretches), once with its own winter frames as
// queries (frames it learned from) and once with its peers' (places whose
// winter it never saw: each query frame counts once per robot that scores
// it, so HOG on these queries is the baseline row).
struct MetricRows {
  std::vector<Row> rows;  // own, own over sequences, peers, peers over ...
  std::string peers_by_length;  // QueryScorer::ByLength of the peers' rows
};
absl::StatusOr<MetricRows> MetricPass(const Setup& classical,
                                      std::vector<Drive> drives,
                                      client::Client& observer) {
  Setup setup = LearningSetup(classical, "-learned");
  setup.learn_metric = true;
  std::printf(
      "\nLearning pass: fleet %s, the robots learn the metric head on the "
      "%s code (fleetmem-robot --learn)\n",
      setup.fleet_id.c_str(), classical.encoder->version().c_str());
  std::fflush(stdout);
  if (absl::Status ran = RunLearningFleet(setup, drives, observer); !ran.ok()) {
    return ran;
  }
  absl::StatusOr<SeasonCodes> codes =
      CodesOf(setup, drives, [&](const cv::Mat& grey) {
        return classical.encoder->EncodeImage(grey);
      });
  if (!codes.ok()) return codes.status();
  const std::string head_rows = "HOG + metric head learned by each robot, ";
  QueryScorer own, peers;
  double own_ms = 0.0, peers_ms = 0.0;
  for (size_t d = 0; d < drives.size(); ++d) {
    const std::string path = absl::StrCat(
        setup.work_dir, "/", drives[d].robot_id, "-winter/metric-head.bin");
    absl::StatusOr<std::string> bytes = files::ReadFile(path);
    if (!bytes.ok()) return bytes.status();
    absl::StatusOr<robot::gpl::MetricHead> head =
        robot::gpl::MetricHead::Deserialize(
            *bytes, int(classical.encoder->dimension()));
    if (!head.ok()) {
      return absl::DataLossError(
          absl::StrCat(path, ": ", head.status().message()));
    }
    if (!head->fitted()) {
      return absl::FailedPreconditionError(
          absl::StrCat(path, ": the robot's head was never fitted"));
    }
    const DescribeFn describe = [&](std::span<const std::vector<float>> z) {
      return head->Describe(z);
    };
    for (absl::Status s :
         {ScoreWinter(describe, *codes, Queries::kOwn, d, own, own_ms),
          ScoreWinter(describe, *codes, Queries::kPeers, d, peers, peers_ms)}) {
      if (!s.ok()) return s;
    }
  }
  MetricRows rows;
  rows.peers_by_length = peers.ByLength();
  const size_t map_size = codes->summer.size();
  const double own_query_ms = own_ms / std::max<size_t>(own.Single().size(), 1);
  const double peers_query_ms =
      peers_ms / std::max<size_t>(peers.Single().size(), 1);
  for (const auto& [scorer, what, query_ms] :
       {std::tuple<QueryScorer*, const char*, double>{
            &own, "its own winter frames (learned from; all summer frames)",
            own_query_ms},
        {&peers, "its peers' winter frames (never seen; all summer frames)",
         peers_query_ms}}) {
    Row single = MapRow(absl::StrCat(head_rows, what), map_size);
    single.ranks = scorer->Single();
    single.query_ms = query_ms;
    Row sequence = MapRow(
        absl::StrCat(head_rows, what, ", sequences of ", Flags().sequence),
        map_size);
    sequence.ranks = scorer->Sequence();
    sequence.query_ms = query_ms;
    rows.rows.push_back(std::move(single));
    rows.rows.push_back(std::move(sequence));
  }
  return rows;
}

// The GPL pass (--gpl-model): the same drives in a fleet of their own with
// the fleet's GPL model, learning every segment. Rows: the frozen fleet
// model and each robot's learned model after winter, scored like the
// baseline (descriptors F(E(q))).
absl::StatusOr<std::vector<Row>> GplPass(const Setup& classical,
                                         std::vector<Drive> drives,
                                         client::Client& observer) {
  Setup setup = LearningSetup(classical, "-gpl");
  setup.gpl_model = Flags().gpl_model;
  std::printf(
      "\nGPL pass: fleet %s, model %s, the robots learn (%d steps per "
      "segment)\n",
      setup.fleet_id.c_str(), setup.gpl_model.c_str(), Flags().learn_steps);
  std::fflush(stdout);
  if (absl::Status ran = RunLearningFleet(setup, drives, observer); !ran.ok()) {
    return ran;
  }
  // The encoder is frozen: the same codes for the fleet model and every
  // robot's learned copy.
  absl::StatusOr<std::unique_ptr<robot::gpl::GplModel>> fleet_model =
      robot::gpl::GplModel::Load(setup.gpl_model);
  if (!fleet_model.ok()) return fleet_model.status();
  absl::StatusOr<SeasonCodes> codes =
      CodesOf(setup, drives,
              [&](const cv::Mat& grey) -> absl::StatusOr<std::vector<float>> {
                absl::StatusOr<std::vector<std::vector<float>>> z =
                    (*fleet_model)->Encode(std::span<const cv::Mat>(&grey, 1));
                if (!z.ok()) return z.status();
                return std::move((*z)[0]);
              });
  if (!codes.ok()) return codes.status();
  auto describe_with = [](robot::gpl::GplModel& model) -> DescribeFn {
    return [&model](std::span<const std::vector<float>> z) {
      return model.Describe(z);
    };
  };
  Row frozen =
      MapRow(absl::StrCat("GPL fleet model ", (*fleet_model)->version(),
                          ", before learning (all summer frames)"),
             codes->summer.size());
  Row learned = MapRow(
      "GPL learned by each robot (summer + winter drives; all summer frames)",
      codes->summer.size());
  double frozen_ms = 0.0, learned_ms = 0.0;
  QueryScorer frozen_scorer, learned_scorer;
  if (absl::Status s = ScoreWinter(describe_with(**fleet_model), *codes,
                                   Queries::kAll, 0, frozen_scorer, frozen_ms);
      !s.ok()) {
    return s;
  }
  frozen.ranks = frozen_scorer.Single();
  for (size_t d = 0; d < drives.size(); ++d) {
    const std::string path = absl::StrCat(
        setup.work_dir, "/", drives[d].robot_id, "-winter/gpl-learned.pt");
    absl::StatusOr<std::unique_ptr<robot::gpl::GplModel>> own =
        robot::gpl::GplModel::Load(path);
    if (!own.ok()) return own.status();
    if (absl::Status s =
            ScoreWinter(describe_with(**own), *codes, Queries::kOwn, d,
                        learned_scorer, learned_ms);
        !s.ok()) {
      return s;
    }
  }
  learned.ranks = learned_scorer.Single();
  frozen.query_ms = frozen_ms / std::max<size_t>(frozen.ranks.size(), 1);
  learned.query_ms = learned_ms / std::max<size_t>(learned.ranks.size(), 1);
  return std::vector<Row>{frozen, learned};
}

// The demo's fleet, data and robots from the flags: the two seasons' frames
// (the same numbers in both), the encoder, the robot binary beside this one.
absl::StatusOr<Setup> MakeSetup() {
  Setup setup;
  setup.fleet_id = Flags().fleet;
  if (setup.fleet_id.empty()) {
    setup.fleet_id = absl::StrCat(
        "nordland-demo-",
        absl::FormatTime("%Y%m%d-%H%M%S", absl::Now(), absl::UTCTimeZone()));
  }
  setup.server = Flags().server;
  const std::string root = Flags().data + "/nordland";
  setup.summer_dir = root + "/summer";
  setup.winter_dir = root + "/winter";
  absl::StatusOr<std::vector<int>> summer =
      robot::ListNordlandFrames(setup.summer_dir);
  if (!summer.ok()) return summer.status();
  absl::StatusOr<std::vector<int>> winter =
      robot::ListNordlandFrames(setup.winter_dir);
  if (!winter.ok()) return winter.status();
  if (*summer != *winter) {
    return absl::FailedPreconditionError(
        absl::StrCat(setup.summer_dir, " and ", setup.winter_dir,
                     " do not hold the same frames"));
  }
  setup.numbers = *std::move(summer);
  setup.encoder_name = Flags().encoder;
  absl::StatusOr<std::unique_ptr<robot::ImageEncoder>> encoder =
      robot::NewImageEncoderByName(setup.encoder_name);
  if (!encoder.ok()) return encoder.status();
  setup.encoder = *std::move(encoder);
  setup.segment_size = std::max(1, Flags().segment_size);
  setup.robot_binary = Flags().robot_binary;
  if (setup.robot_binary.empty()) {
    setup.robot_binary =
        (std::filesystem::canonical("/proc/self/exe").parent_path() /
         "fleetmem-robot")
            .string();
  }
  setup.work_dir = absl::StrCat(Flags().work_dir, "/", setup.fleet_id);
  return setup;
}

// After the summer drives: the fleet's log applied, the rest consolidated,
// and the memory as it stands.
struct Consolidated {
  v1::GetStatsResponse before;  // applied, before the Consolidate call
  v1::ConsolidateResponse consolidate;
  double consolidate_ms = 0.0;
  v1::GetStatsResponse stats;  // after it
  // Robot batches the Consolidate call consolidated.
  uint64_t final_batches() const {
    return stats.consolidations() - before.consolidations();
  }
};

absl::StatusOr<Consolidated> ConsolidateAndLook(const Setup& setup,
                                                client::Client& observer) {
  Consolidated done;
  // The robots' uploads were acknowledged when durable: the memory is read
  // once the fleet's log is applied through them.
  absl::StatusOr<v1::GetStatsResponse> before =
      observer.GetStats(setup.fleet_id);
  const auto give_up = Clock::now() + std::chrono::seconds(120);
  while (before.ok() &&
         before->applied_through() < before->acknowledged_through() &&
         Clock::now() < give_up) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    before = observer.GetStats(setup.fleet_id);
  }
  if (!before.ok()) return before.status();
  done.before = *std::move(before);
  const auto consolidate_start = Clock::now();
  absl::StatusOr<v1::ConsolidateResponse> consolidated =
      observer.Consolidate(setup.fleet_id);
  done.consolidate_ms = MillisSince(consolidate_start);
  if (!consolidated.ok()) return consolidated.status();
  done.consolidate = *std::move(consolidated);
  const v1::ConsolidateResponse& c = done.consolidate;
  std::printf(
      "consolidate: %llu pending traces -> %llu clusters added, %llu traces "
      "downsampled, %llu clusters forgotten; memory now %llu clusters, %llu "
      "traces (%.1f ms)\n",
      static_cast<unsigned long long>(c.consolidated_traces()),
      static_cast<unsigned long long>(c.clusters_added()),
      static_cast<unsigned long long>(c.downsampled_traces()),
      static_cast<unsigned long long>(c.clusters_forgotten()),
      static_cast<unsigned long long>(c.clusters()),
      static_cast<unsigned long long>(c.traces()), done.consolidate_ms);
  absl::StatusOr<v1::GetStatsResponse> stats =
      observer.GetStats(setup.fleet_id);
  if (!stats.ok()) return stats.status();
  done.stats = *std::move(stats);
  for (const v1::RobotStats& robot : done.stats.robots()) {
    std::printf(
        "stats: %s holds %llu of its %llu uploaded traces (max seq "
        "%llu)\n",
        robot.robot_id().c_str(),
        static_cast<unsigned long long>(robot.traces()),
        static_cast<unsigned long long>(robot.received()),
        static_cast<unsigned long long>(robot.max_seq()));
  }
  absl::StatusOr<EventSummary> events =
      ReadEvents(observer, setup.fleet_id, done.stats.last_event_id());
  if (!events.ok()) return events.status();
  std::printf("events: %llu clusters added, %llu forgotten\n",
              static_cast<unsigned long long>(events->added),
              static_cast<unsigned long long>(events->forgotten));
  std::fflush(stdout);
  return done;
}

// The baseline: every summer code of the drives, searched by brute force
// with each winter code (its row), and how many winter places the memory
// still holds a trace near (`covered` of `queries`).
struct Baseline {
  Row row;
  Row sequence_row;       // the same queries over sequences
  std::string by_length;  // QueryScorer::ByLength
  size_t size = 0;        // codes
  size_t covered = 0;
  size_t queries = 0;
};

absl::StatusOr<Baseline> RunBaseline(const Setup& setup,
                                     const std::vector<Drive>& drives,
                                     client::Client& observer) {
  Baseline result;
  result.row.system = "all traces, no memory bound (baseline)";
  robot::BruteForceIndex baseline(setup.encoder->dimension());
  for (const Drive& drive : drives) {
    for (size_t i = drive.stretch.begin; i < drive.stretch.end; ++i) {
      absl::StatusOr<std::vector<float>> code =
          EncodeFrame(setup, setup.summer_dir, setup.numbers[i]);
      if (!code.ok()) return code.status();
      baseline.Add(*code, setup.numbers[i]);
    }
  }
  std::vector<double> local_ms;
  QueryScorer scorer;
  for (const Drive& drive : drives) {
    scorer.Restart();
    for (size_t i = drive.stretch.begin; i < drive.stretch.end; ++i) {
      const core::Place place{.x = static_cast<double>(setup.numbers[i])};
      absl::StatusOr<std::vector<float>> code =
          EncodeFrame(setup, setup.winter_dir, setup.numbers[i]);
      if (!code.ok()) return code.status();
      const auto start = Clock::now();
      const auto found = baseline.SearchScored(*code, kSequenceCandidates);
      local_ms.push_back(MillisSince(start));
      scorer.Score(found, place.x);
      // Does the memory still hold the place at all (after forgetting)?
      v1::QueryPlaceRequest near;
      near.set_fleet_id(setup.fleet_id);
      near.mutable_code()->Assign(code->begin(), code->end());
      near.set_k(1);
      near.mutable_near()->set_x(place.x);
      near.set_radius_m(kToleranceUnits);
      absl::StatusOr<std::vector<v1::PlaceMatch>> held =
          observer.QueryPlace(near);
      if (!held.ok()) return held.status();
      result.covered += held->empty() ? 0 : 1;
      ++result.queries;
    }
  }
  result.size = baseline.size();
  result.row.ranks = scorer.Single();
  result.row.traces = absl::StrCat(baseline.size());
  result.row.clusters = "-";
  result.row.consolidation_ms = "-";
  result.row.query_ms = std::accumulate(local_ms.begin(), local_ms.end(), 0.0) /
                        std::max<size_t>(local_ms.size(), 1);
  result.sequence_row = result.row;
  result.sequence_row.system =
      absl::StrCat("all traces, no memory bound, sequences of ",
                   Flags().sequence, " (baseline)");
  result.sequence_row.ranks = scorer.Sequence();
  result.by_length = scorer.ByLength();
  return result;
}

// The fleet memory's row: the winter robots' relocalisations, single
// frames or (`sequence`) re-ranked over their last --sequence frames.
Row MemoryRow(const std::vector<Drive>& drives, const Consolidated& done,
              bool sequence) {
  Row row;
  row.system = sequence ? absl::StrCat(
                              "fleet memory, the same robots over "
                              "sequences of ",
                              Flags().sequence)
                        : "fleet memory (server, winter fleetmem-robots)";
  double query_ms_sum = 0.0;
  for (const Drive& drive : drives) {
    const core::FirstCorrectRanks ranks =
        sequence ? robot::SequenceRanks(drive.winter.counters())
                 : robot::RelocalisationRanks(drive.winter.counters());
    row.ranks.insert(row.ranks.end(), ranks.begin(), ranks.end());
    query_ms_sum += drive.winter.counters().relocalisation_ms_total();
  }
  row.traces = absl::StrCat(done.stats.traces());
  row.clusters = absl::StrCat(done.stats.clusters());
  row.query_ms = row.ranks.empty() ? 0.0 : query_ms_sum / row.ranks.size();
  row.consolidation_ms =
      done.final_batches() > 0
          ? absl::StrFormat("%.1f", done.consolidate_ms / done.final_batches())
          : "-";
  return row;
}

// What the results table's numbers are, under it.
std::string Notes(const Setup& setup, const std::vector<Drive>& drives,
                  const Row& memory_row, const Consolidated& done,
                  const Baseline& baseline, double summer_s, double winter_s) {
  uint64_t uploaded = 0;
  for (const Drive& drive : drives) {
    uploaded += drive.summer.counters().traces_uploaded();
  }
  const v1::GetStatsResponse& stats = done.stats;
  std::string notes = absl::StrFormat(
      "- %zu winter relocalisations by %zu fleetmem-robot processes (query "
      "only) over the stretches the same robots drove in summer; correct if "
      "a match is within +-2 files (+-%.0f units).\n"
      "- Summer: %zu robot processes uploaded %d traces in %.1f s "
      "(store-and-forward through each robot's own queue); winter: %.1f s.\n"
      "- Encoder %s (%zu dims). Memory bounds of the fleet: N_max = %d "
      "traces per cluster, K_max = %d clusters; %d consolidations, %d "
      "clusters forgotten.\n"
      "- Time per consolidation: %s.\n"
      "- Time per query: fleet memory = the robots' QueryPlace round trip "
      "(k = %d, of which the first 6 score a single frame) while driving; "
      "baseline = in-process brute force over %zu "
      "codes.\n"
      "- The memory still holds a trace within +-2 files of %zu of %zu "
      "query places (%.1f%%): an upper bound of its recall.\n"
      "- Robots: a robot's peers are the other robots; its dynamic memory "
      "(capacity 1,000) is refreshed from the fleet at its start and after "
      "every segment (Eq. 18), and every segment replays 64 traces from it "
      "(Eq. 19).\n"
      "- Sequence rows: each query's %d nearest re-ranked by the best path "
      "over its drive's last %d frames whose places agree with the distance "
      "driven (fleetmem-robot --sequence; docs/robot.md); the fleet memory's "
      "from the robots' own QueryPlace answers (k = %d), with the gaps "
      "forgetting left.\n",
      memory_row.ranks.size(), drives.size(), kToleranceUnits, drives.size(),
      uploaded, summer_s, winter_s, setup.encoder->version(),
      setup.encoder->dimension(), stats.max_traces_per_cluster(),
      stats.max_clusters(), stats.consolidations(), stats.clusters_forgotten(),
      done.final_batches() > 0
          ? absl::StrFormat(
                "the final Consolidate call (client round trip, %.1f ms) "
                "divided by the %d robot batches it consolidated (%d traces)",
                done.consolidate_ms, done.final_batches(),
                done.consolidate.consolidated_traces())
          : std::string("not measured: the robots' uploads consolidated "
                        "every batch (stretches a multiple of the segment "
                        "size), so the final Consolidate call had nothing "
                        "to do"),
      kSequenceCandidates, baseline.size, baseline.covered, baseline.queries,
      100.0 * baseline.covered / std::max<size_t>(baseline.queries, 1),
      kSequenceCandidates, Flags().sequence, kSequenceCandidates);
  if (Flags().learn) {
    notes +=
        "- Learned rows: the same robots drove again in a fleet of their own "
        "with fleetmem-robot --learn; each robot's metric head on the HOG "
        "code (after its winter drive) describes every summer frame (the "
        "baseline's map) and the winter queries. Its own winter frames are "
        "frames it fitted its head on (pairs with the fleet's summer traces "
        "of the same places); its peers' winter frames are places whose "
        "winter it never saw. docs/results.md holds the held-out protocol "
        "(fleetmem-eval lifelong).\n";
  }
  return notes;
}

// The results: the table of rows, the robots' table and the notes, on
// stdout and in --results-md.
absl::Status Report(const Setup& setup, const std::vector<Drive>& drives,
                    const std::vector<Row>& rows, const std::string& notes) {
  const std::string table = Table(rows);
  const std::string robots = RobotTable(setup, drives);
  std::printf("\nResults (fleet %s)\n\n%s\n%s\n%s\n%s\n",
              setup.fleet_id.c_str(), table.c_str(), robots.c_str(),
              notes.c_str(), kAttribution);
  const std::string md_path = Flags().results_md;
  if (!md_path.empty()) {
    std::ofstream md(md_path);
    md << "# fleetmem demo: Nordland summer -> winter, fleet of "
       << drives.size() << " fleetmem-robot processes\n\n"
       << table << "\n"
       << robots << "\n"
       << notes << "\n"
       << kAttribution << "\n";
    if (!md) return absl::InternalError(absl::StrCat("cannot write ", md_path));
    std::printf("Results table written to %s\n", md_path.c_str());
  }
  return absl::OkStatus();
}

absl::Status Run() {
  absl::StatusOr<Setup> made = MakeSetup();
  if (!made.ok()) return made.status();
  Setup& setup = *made;
  absl::StatusOr<std::vector<robot::Stretch>> stretches =
      robot::SpreadStretches(setup.numbers.size(), Flags().robots,
                             Flags().stretch_length);
  if (!stretches.ok()) return stretches.status();
  std::vector<Drive> drives(stretches->size());
  for (size_t r = 0; r < drives.size(); ++r) {
    drives[r].robot_id = absl::StrCat("robot-", r + 1);
    drives[r].stretch = (*stretches)[r];
  }
  client::ClientOptions client_options;
  client_options.target = setup.server;
  std::unique_ptr<client::Client> observer =
      client::Client::Create(client_options);
  std::printf(
      "fleetmem demo: fleet %s on %s, %zu fleetmem-robot processes x %d "
      "summer frames, then the same stretches in winter; encoder %s (%zu "
      "dims), data %s/nordland, robot data dirs under %s\n",
      setup.fleet_id.c_str(), setup.server.c_str(), drives.size(),
      Flags().stretch_length, setup.encoder->version().c_str(),
      setup.encoder->dimension(), Flags().data.c_str(), setup.work_dir.c_str());
  std::fflush(stdout);

  // 1. Summer: the robots drive and upload, each its own process. ----------
  const auto summer_start = Clock::now();
  absl::Status ran = RunRobots(setup, drives, "summer", /*query_only=*/false);
  if (!ran.ok()) return ran;
  const double summer_s = MillisSince(summer_start) / 1000.0;

  // 2. Consolidate the rest, then look at the memory. ------------------------
  absl::StatusOr<Consolidated> done = ConsolidateAndLook(setup, *observer);
  if (!done.ok()) return done.status();

  // 3. Winter: the same robots relocalise against the fleet memory. --------
  const auto winter_start = Clock::now();
  ran = RunRobots(setup, drives, "winter", /*query_only=*/true);
  if (!ran.ok()) return ran;
  const double winter_s = MillisSince(winter_start) / 1000.0;

  // 4. Results: fleet memory vs every summer code by brute force. ----------
  absl::StatusOr<Baseline> baseline = RunBaseline(setup, drives, *observer);
  if (!baseline.ok()) return baseline.status();
  const Row memory_row = MemoryRow(drives, *done, /*sequence=*/false);
  std::vector<Row> rows = {memory_row,
                           MemoryRow(drives, *done, /*sequence=*/true),
                           baseline->row, baseline->sequence_row};
  std::string by_length = absl::StrCat(
      "- WR by sequence length (frames, in brackets), choosing --sequence: "
      "baseline ",
      baseline->by_length);
  if (Flags().learn) {
    absl::StatusOr<MetricRows> learned = MetricPass(setup, drives, *observer);
    if (!learned.ok()) return learned.status();
    rows.insert(rows.end(), learned->rows.begin(), learned->rows.end());
    absl::StrAppend(&by_length, "; metric head, peers' frames ",
                    learned->peers_by_length);
  }
  by_length += ".\n";
  if (!Flags().gpl_model.empty()) {
    absl::StatusOr<std::vector<Row>> gpl = GplPass(setup, drives, *observer);
    if (!gpl.ok()) return gpl.status();
    rows.insert(rows.end(), gpl->begin(), gpl->end());
  }
  return Report(
      setup, drives, rows,
      Notes(setup, drives, memory_row, *done, *baseline, summer_s, winter_s) +
          by_length);
}

}  // namespace
}  // namespace fleetmem::demo

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem-demo: fleet memory demo on Nordland: three fleetmem-robot "
      "processes share "
      "one memory of the summer route and recognise its places in winter."};
  fleetmem::common::SetUpProgram(app, "fleetmem-demo");
  fleetmem::demo::DemoFlags& flags = fleetmem::demo::Flags();
  app.add_option("--server", flags.server, "fleetmem server, HOST:PORT")
      ->capture_default_str();
  app.add_option(
      "--data", flags.data,
      "shared data folder (holds nordland/summer and nordland/winter; "
      "default: the checkout's ../shared/data)");
  app.add_option(
         "--fleet", flags.fleet,
         "fleet id (default: nordland-demo-<UTC time>, so reruns do not "
         "collide)")
      ->capture_default_str();
  app.add_option("--robots", flags.robots,
                 "robots, each driving its own stretch")
      ->capture_default_str();
  app.add_option("--stretch-length,--stretch_length", flags.stretch_length,
                 "frames per robot stretch")
      ->capture_default_str();
  app.add_option("--results-md,--results_md", flags.results_md,
                 "also write the results table as Markdown to this file")
      ->capture_default_str();
  app.add_option("--encoder", flags.encoder,
                 "image code (see fleetmem-encoder-eval for the variants)")
      ->capture_default_str();
  app.add_option("--segment-size,--segment_size", flags.segment_size,
                 "observations per robot segment")
      ->capture_default_str();
  app.add_option("--work-dir,--work_dir", flags.work_dir,
                 "the robots' data dirs go below (one per robot and season)")
      ->capture_default_str();
  app.add_option("--robot-binary,--robot_binary", flags.robot_binary,
                 "fleetmem-robot (default: beside this program)")
      ->capture_default_str();
  app.add_option(
         "--gpl-model,--gpl_model", flags.gpl_model,
         "a fleet GPL model (fleetmem-eval pretrain): the same robots drive "
         "again in a second fleet with it and learn (--learn), and the table "
         "shows the learned model beside the classical code")
      ->capture_default_str();
  app.add_option("--learn-steps,--learn_steps", flags.learn_steps,
                 "place-head steps per segment of the GPL robots")
      ->capture_default_str();
  app.add_flag(
      "--learn", flags.learn,
      "the same robots drive again in a fleet of their own that learns "
      "(fleetmem-robot --learn: the metric head on the fleet code), and "
      "the table shows each robot's learned head beside the classical "
      "code on the same map");
  app.add_flag("--sequential-robots,--sequential_robots",
               flags.sequential_robots,
               "run the robots one after another instead of side by side: the "
               "server then receives their segments in a fixed order, so a run "
               "with a fixed --fleet repeats exactly");
  app.add_option("--sequence", flags.sequence,
                 "frames per sequence of the sequence rows (fleetmem-robot "
                 "--sequence)")
      ->capture_default_str()
      ->check(CLI::Range(2, 100));
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  const absl::Status status = fleetmem::demo::Run();
  if (!status.ok()) {
    std::cerr << "fleetmem-demo: " << status << "\n";
    return 1;
  }
  return 0;
}
