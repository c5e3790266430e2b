// Integration tests of fleetmem-server's durability: a SIGKILLed server
// restarted on the same RocksDB data directory has everything it
// acknowledged, and SIGTERM shuts it down cleanly (exit code 0) even with
// streams in flight.
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <initializer_list>
#include <iostream>
#include <map>
#include <mutex>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "fleetmem/v1/memory.grpc.pb.h"
#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/util/message_differencer.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
#include "tests/integration_fixture.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

using ::google::protobuf::util::MessageDifferencer;

constexpr size_t kDim = 32;

struct RobotPlan {
  std::string robot_id;
  size_t count;
};

TraceSpec SpecOf(const RobotPlan& plan) {
  return TraceSpec{
      .robot_id = plan.robot_id,
      .count = plan.count,
      .dimension = kDim,
      .reward = [](uint64_t seq) { return 0.2f + 0.1f * (seq % 7); }};
}

// `expected` and `actual` are equal; the message lists the differences.
void ExpectSameMessage(const google::protobuf::Message& expected,
                       const google::protobuf::Message& actual,
                       const std::string& what) {
  std::string diff;
  MessageDifferencer differencer;
  differencer.ReportDifferencesToString(&diff);
  EXPECT_TRUE(differencer.Compare(expected, actual))
      << what << " differs after the restart:\n"
      << diff;
}

// What a client can observe of a fleet, to compare across restarts.
struct Observation {
  v1::GetStatsResponse stats;
  std::vector<v1::MemoryEvent> events;
  std::vector<v1::QueryPlaceResponse> queries;
};

// `after` answers as `before` did: GetStats, every event (if
// `with_events`) and every QueryPlace (each match's replay_count and
// cluster_id included).
void ExpectSameObservation(const Observation& before, const Observation& after,
                           bool with_events) {
  ExpectSameMessage(before.stats, after.stats, "GetStats");
  if (with_events) {
    ASSERT_EQ(after.events.size(), before.events.size());
    for (size_t i = 0; i < before.events.size(); ++i) {
      ExpectSameMessage(before.events[i], after.events[i],
                        "event " + std::to_string(i));
    }
  }
  ASSERT_EQ(after.queries.size(), before.queries.size());
  for (size_t i = 0; i < before.queries.size(); ++i) {
    ExpectSameMessage(before.queries[i], after.queries[i],
                      "QueryPlace " + std::to_string(i));
  }
}

class RestartTest : public ServerTest {
 protected:
  // Restarts the server with a configuration file of `text`.
  void RestartWithConfig(const std::string& text) {
    const std::string config = temp_dir().Join("server.textproto");
    std::ofstream(config) << text;
    set_server_args({"--config", config});
    ASSERT_NO_FATAL_FAILURE(StopAndRestart());
  }
  void Observe(const std::string& fleet,
               const std::vector<v1::QueryPlaceRequest>& queries,
               Observation* observation) {
    Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
    ASSERT_TRUE(stats.ok()) << Describe(stats.status);
    observation->stats = stats.response;
    Reply<std::vector<v1::MemoryEvent>> events =
        ReadEvents(stub(), fleet, 0, stats.response.last_event_id());
    ASSERT_TRUE(events.ok()) << Describe(events.status);
    observation->events = events.response;
    observation->queries.clear();
    for (const v1::QueryPlaceRequest& request : queries) {
      Reply<v1::QueryPlaceResponse> reply = QueryPlace(stub(), request);
      ASSERT_TRUE(reply.ok()) << Describe(reply.status);
      observation->queries.push_back(reply.response);
    }
  }
};

// A QueryPlace (k = `k`) of `fleet` for the code of traces `seqs` of each
// of `plans`.
std::vector<v1::QueryPlaceRequest> QueriesOfTheirTraces(
    const std::string& fleet, const std::vector<RobotPlan>& plans,
    std::initializer_list<uint64_t> seqs = {1, 77, 150}, int k = 5) {
  std::vector<v1::QueryPlaceRequest> queries;
  for (const RobotPlan& plan : plans) {
    for (uint64_t seq : seqs) {
      v1::QueryPlaceRequest& request = queries.emplace_back();
      request.set_fleet_id(fleet);
      const v1::MemoryTrace trace = MakeTrace(SpecOf(plan), seq);
      for (float value : trace.code()) request.add_code(value);
      request.set_k(k);
    }
  }
  return queries;
}

TEST_F(RestartTest, KilledServerKeepsEverythingAcknowledged) {
  const std::string fleet = "fleet-durable";
  // 3,000 traces; the counts leave 400 pending (count % 200 per robot).
  const std::vector<RobotPlan> plans = {{"robot-a", 650},
                                        {"robot-b", 550},
                                        {"robot-c", 600},
                                        {"robot-d", 640},
                                        {"robot-e", 560}};
  std::vector<uint64_t> acknowledged(plans.size(), 0);
  std::vector<std::string> errors(plans.size());
  std::vector<std::thread> threads;
  for (size_t r = 0; r < plans.size(); ++r) {
    threads.emplace_back([&, r] {
      std::unique_ptr<v1::MemoryService::Stub> robot_stub =
          MakeStub(server().address());
      std::vector<v1::MemoryTrace> traces = MakeTraces(SpecOf(plans[r]));
      for (size_t begin = 0; begin < traces.size(); begin += 100) {
        std::span<const v1::MemoryTrace> part = std::span(traces).subspan(
            begin, std::min<size_t>(100, traces.size() - begin));
        Reply<v1::UploadTracesResponse> reply =
            UploadTraces(*robot_stub, fleet, part, /*batch=*/50);
        if (!reply.ok()) {
          errors[r] = Describe(reply.status);
          return;
        }
        acknowledged[r] += reply.response.accepted();
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  uint64_t total = 0, pending = 0, consolidations = 0;
  for (size_t r = 0; r < plans.size(); ++r) {
    ASSERT_EQ(errors[r], "") << plans[r].robot_id;
    ASSERT_EQ(acknowledged[r], plans[r].count) << plans[r].robot_id;
    total += acknowledged[r];
    pending += plans[r].count % 200;
    consolidations += plans[r].count / 200;
  }
  ASSERT_EQ(total, 3000u);

  // Crash right after the last acknowledgement: no clean shutdown.
  ASSERT_NO_FATAL_FAILURE(KillAndRestart());

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.code_dimension(), kDim);
  EXPECT_EQ(stats.response.encoder_version(), "enc-v1");
  EXPECT_EQ(stats.response.pending_traces(), pending);
  EXPECT_EQ(stats.response.consolidations(), consolidations);
  EXPECT_LE(stats.response.clusters(), 100u);
  EXPECT_GT(stats.response.traces(), 0u);
  uint64_t received = 0;
  for (const RobotPlan& plan : plans) {
    const v1::RobotStats* robot = FindRobot(stats.response, plan.robot_id);
    ASSERT_NE(robot, nullptr) << plan.robot_id;
    EXPECT_EQ(robot->received(), plan.count) << plan.robot_id;
    EXPECT_EQ(robot->max_seq(), plan.count) << plan.robot_id;
    EXPECT_EQ(robot->pending_traces(), plan.count % 200) << plan.robot_id;
    received += robot->received();
  }
  EXPECT_EQ(received, total) << "acknowledged traces were lost";

  // Replay some traces (acknowledged mutations too), then observe the fleet.
  for (int round = 0; round < 2; ++round) {
    Reply<v1::SampleReplayResponse> sample =
        SampleReplay(stub(), fleet, "robot-a", 250);
    ASSERT_TRUE(sample.ok()) << Describe(sample.status);
  }
  std::vector<v1::QueryPlaceRequest> queries;
  for (const RobotPlan& plan : plans) {
    for (uint64_t seq : {uint64_t{1}, uint64_t{333}, uint64_t{plan.count}}) {
      v1::QueryPlaceRequest& request = queries.emplace_back();
      request.set_fleet_id(fleet);
      v1::MemoryTrace trace = MakeTrace(SpecOf(plan), seq);
      for (float value : trace.code()) request.add_code(value);
      request.set_k(10);
      if (seq == 333) {  // with a position prior
        *request.mutable_near() = trace.pose();
        request.set_radius_m(400.0);
      }
    }
  }
  Observation before;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &before));
  ASSERT_FALSE(before.events.empty());

  ASSERT_NO_FATAL_FAILURE(KillAndRestart());

  Observation after;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &after));
  ExpectSameObservation(before, after, /*with_events=*/true);

  // Every trace is still known: a full retry is all duplicates.
  uint64_t duplicates = 0, accepted = 0;
  for (const RobotPlan& plan : plans) {
    Reply<v1::UploadTracesResponse> reply =
        UploadTraces(stub(), fleet, MakeTraces(SpecOf(plan)), /*batch=*/500);
    ASSERT_TRUE(reply.ok()) << Describe(reply.status);
    duplicates += reply.response.duplicates();
    accepted += reply.response.accepted();
  }
  EXPECT_EQ(accepted, 0u);
  EXPECT_EQ(duplicates, total);

  // Event ids continue after the restart (never reused).
  const uint64_t last_before = before.stats.last_event_id();
  Reply<v1::UploadTracesResponse> more = UploadTraces(
      stub(), fleet, MakeTraces(SpecOf({"robot-f", 200})), /*batch=*/100);
  ASSERT_TRUE(more.ok()) << Describe(more.status);
  EXPECT_EQ(more.response.consolidations(), 1u);
  Reply<v1::GetStatsResponse> latest = GetStats(stub(), fleet);
  ASSERT_TRUE(latest.ok()) << Describe(latest.status);
  ASSERT_GT(latest.response.last_event_id(), last_before);
  Reply<std::vector<v1::MemoryEvent>> fresh =
      ReadEvents(stub(), fleet, last_before, latest.response.last_event_id());
  ASSERT_TRUE(fresh.ok()) << Describe(fresh.status);
  ASSERT_FALSE(fresh.response.empty());
  EXPECT_EQ(fresh.response.front().id(), last_before + 1);
  for (const v1::MemoryEvent& event : fresh.response) {
    EXPECT_GT(event.id(), last_before);
  }

  // Replay counts survived: one more draw of everything adds exactly one.
  std::map<std::pair<std::string, uint64_t>, uint32_t> counts_before;
  for (const v1::QueryPlaceResponse& query : before.queries) {
    for (const v1::PlaceMatch& match : query.matches()) {
      counts_before[{match.trace().robot_id(), match.trace().seq()}] =
          match.trace().replay_count();
    }
  }
  Reply<v1::SampleReplayResponse> everything =
      SampleReplay(stub(), fleet, "robot-b", 10000);
  ASSERT_TRUE(everything.ok()) << Describe(everything.status);
  size_t checked = 0, replayed_before = 0;
  for (const v1::MemoryTrace& trace : everything.response.traces()) {
    auto it = counts_before.find({trace.robot_id(), trace.seq()});
    if (it == counts_before.end()) continue;
    ++checked;
    replayed_before += it->second > 0 ? 1 : 0;
    EXPECT_EQ(trace.replay_count(), it->second + 1)
        << trace.robot_id() << "/" << trace.seq();
  }
  EXPECT_GT(checked, 0u);
  EXPECT_GT(replayed_before, 0u) << "precondition: some matches were replayed";
}

// A server that saves index snapshots while serving (every second here)
// and is then killed restarts from its last snapshot, reconciled with what
// was stored after it, instead of rebuilding its place index; a client sees
// the same state as before the kill.
TEST_F(RestartTest, KilledServerRestartsFromItsPeriodicIndexSnapshot) {
  ASSERT_NO_FATAL_FAILURE(
      RestartWithConfig("index_snapshot_interval_seconds: 1\n"
                        "index_snapshot_min_codes: 0\n"));
  const std::string fleet = "fleet-periodic-snapshot";
  ASSERT_TRUE(
      UploadTraces(stub(), fleet, MakeTraces(SpecOf({"robot-a", 230}))).ok());
  // The first periodic snapshot.
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (server().Output().find("index snapshot of") == std::string::npos) {
    ASSERT_LT(std::chrono::steady_clock::now(), deadline)
        << "no periodic index snapshot within 20 s";
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  // Stored after it: another robot's segment and more pending traces.
  ASSERT_TRUE(
      UploadTraces(stub(), fleet, MakeTraces(SpecOf({"robot-b", 260}))).ok());
  const std::vector<v1::QueryPlaceRequest> queries = QueriesOfTheirTraces(
      fleet, {{"robot-a", 230}, {"robot-b", 260}}, {1, 99, 201, 230},
      /*k=*/10);
  Observation before;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &before));

  ASSERT_NO_FATAL_FAILURE(KillAndRestart());

  EXPECT_NE(server().Output().find("index snapshot reconciled"),
            std::string::npos)
      << "the restart did not use the periodic snapshot";
  Observation after;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &after));
  ExpectSameObservation(before, after, /*with_events=*/false);
}

// A robot's traces left after a delete of them, as stored: every one, or
// none. The server is killed at a random moment of 20 deletes (before the
// call is logged, between its log entry and its apply, or after); after
// the restart each robot's traces are all there or all gone, and a delete
// the server answered is never undone.
TEST_F(RestartTest, ADeleteKilledAtAnyMomentIsAllOrNothing) {
  const std::string fleet = "fleet-deletes";
  constexpr int kTrials = 20;
  constexpr size_t kPerRobot = 250;  // a consolidated segment and pending
  for (int r = 0; r < kTrials; ++r) {
    const RobotPlan plan{"robot-" + std::to_string(r), kPerRobot};
    Reply<v1::UploadTracesResponse> reply =
        UploadTraces(stub(), fleet, MakeTraces(SpecOf(plan)), /*batch=*/250);
    ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  }
  Reply<v1::GetStatsResponse> filled = GetStatsApplied(stub(), fleet);
  ASSERT_TRUE(filled.ok()) << Describe(filled.status);
  // What each robot holds (forgetting merged and downsampled some).
  std::vector<uint64_t> held_before(kTrials);
  for (int r = 0; r < kTrials; ++r) {
    const v1::RobotStats* robot =
        FindRobot(filled.response, "robot-" + std::to_string(r));
    ASSERT_NE(robot, nullptr);
    held_before[r] = robot->traces() + robot->pending_traces();
    ASSERT_GT(held_before[r], 0u);
  }
  std::mt19937 rng(2026);
  int answered = 0, undone = 0, partial = 0, applied = 0;
  for (int trial = 0; trial < kTrials; ++trial) {
    const std::string robot = "robot-" + std::to_string(trial);
    std::atomic<bool> acknowledged{false};
    std::thread deleter([&] {
      v1::DeleteTracesRequest request;
      request.set_fleet_id(fleet);
      request.set_robot_id(robot);
      v1::DeleteTracesResponse response;
      auto context = MakeContext();
      if (MakeStub(server().address())
              ->DeleteTraces(context.get(), request, &response)
              .ok()) {
        acknowledged = response.deleted() == held_before[trial];
      }
    });
    // 0 to 20 ms after the call is sent (a delete is answered after 10-15 ms
    // here): before it is logged, between its
    // log entry and its apply, or after its answer.
    std::this_thread::sleep_for(std::chrono::microseconds(
        std::uniform_int_distribution<int>(0, 20000)(rng)));
    ASSERT_NO_FATAL_FAILURE(KillAndRestart());
    deleter.join();
    Reply<v1::GetStatsResponse> stats = GetStatsApplied(stub(), fleet);
    ASSERT_TRUE(stats.ok()) << Describe(stats.status);
    for (int r = 0; r <= trial; ++r) {
      const v1::RobotStats* left =
          FindRobot(stats.response, "robot-" + std::to_string(r));
      ASSERT_NE(left, nullptr);
      const uint64_t held = left->traces() + left->pending_traces();
      if (held != 0 && held != held_before[r]) ++partial;
      if (r < trial) EXPECT_EQ(held, 0u) << "robot-" << r;
      if (r != trial) continue;
      answered += acknowledged ? 1 : 0;
      applied += held == 0 ? 1 : 0;
      if (acknowledged && held != 0) ++undone;
      EXPECT_TRUE(held == 0 || held == held_before[r])
          << robot << ": " << held << " of " << held_before[r] << " left";
    }
    // Whatever the kill left, the robot's traces go now (a retry).
    v1::DeleteTracesRequest retry;
    retry.set_fleet_id(fleet);
    retry.set_robot_id(robot);
    v1::DeleteTracesResponse response;
    auto context = MakeContext();
    ASSERT_TRUE(stub().DeleteTraces(context.get(), retry, &response).ok());
  }
  EXPECT_EQ(partial, 0);
  EXPECT_EQ(undone, 0) << "a delete the server answered was undone";
  std::cout << "deletes killed: " << kTrials << ", answered before the kill "
            << answered << ", applied after the restart " << applied
            << ", partial " << partial << "\n";
  // Every robot's traces were deleted: the fleet holds none.
  Reply<v1::GetStatsResponse> stats = GetStatsApplied(stub(), fleet);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(), 0u);
}

// DeleteFleet killed at any moment: after the restart the fleet is whole
// or gone, never half; gone if the server answered the delete.
TEST_F(RestartTest, ADeleteFleetKilledAtAnyMomentIsAllOrNothing) {
  constexpr int kTrials = 10;
  std::mt19937 rng(2027);
  int answered = 0, gone = 0, partial = 0, undone = 0;
  for (int trial = 0; trial < kTrials; ++trial) {
    const std::string fleet = "gone-" + std::to_string(trial);
    for (const RobotPlan& plan :
         {RobotPlan{"robot-a", 250}, RobotPlan{"robot-b", 250}}) {
      ASSERT_TRUE(UploadTraces(stub(), fleet, MakeTraces(SpecOf(plan))).ok());
    }
    Reply<v1::GetStatsResponse> filled = GetStatsApplied(stub(), fleet);
    ASSERT_TRUE(filled.ok()) << Describe(filled.status);
    const uint64_t held_before =
        filled.response.traces() + filled.response.pending_traces();
    std::atomic<bool> acknowledged{false};
    std::thread deleter([&] {
      v1::DeleteFleetRequest request;
      request.set_fleet_id(fleet);
      v1::DeleteFleetResponse response;
      auto context = MakeContext();
      if (MakeStub(server().address())
              ->DeleteFleet(context.get(), request, &response)
              .ok()) {
        acknowledged = response.traces_deleted() == held_before;
      }
    });
    std::this_thread::sleep_for(std::chrono::microseconds(
        std::uniform_int_distribution<int>(0, 12000)(rng)));
    ASSERT_NO_FATAL_FAILURE(KillAndRestart());
    deleter.join();
    answered += acknowledged ? 1 : 0;
    Reply<v1::GetStatsResponse> stats = GetStatsApplied(stub(), fleet);
    if (stats.status.error_code() == grpc::StatusCode::NOT_FOUND) {
      ++gone;
    } else {
      ASSERT_TRUE(stats.ok()) << Describe(stats.status);
      const uint64_t held =
          stats.response.traces() + stats.response.pending_traces();
      if (held != held_before) ++partial;
      if (acknowledged) ++undone;
      EXPECT_EQ(held, held_before) << fleet;
    }
    // The id makes a new fleet whatever the kill left (deleted again if
    // the delete did not happen).
    if (stats.ok()) {
      v1::DeleteFleetRequest again;
      again.set_fleet_id(fleet);
      v1::DeleteFleetResponse response;
      ASSERT_TRUE(
          stub().DeleteFleet(MakeContext().get(), again, &response).ok());
    }
    const std::vector<v1::MemoryTrace> fresh =
        MakeTraces(SpecOf(RobotPlan{"robot-a", 5}));
    Reply<v1::UploadTracesResponse> remade = UploadTraces(stub(), fleet, fresh);
    ASSERT_TRUE(remade.ok()) << Describe(remade.status);
    EXPECT_EQ(remade.response.accepted(), 5u) << fleet;
  }
  EXPECT_EQ(partial, 0);
  EXPECT_EQ(undone, 0) << "a fleet deletion the server answered was undone";
  std::cout << "fleet deletions killed: " << kTrials
            << ", answered before the kill " << answered
            << ", gone after the restart " << gone << ", partial " << partial
            << "\n";
}

// A clean stop and start keep everything observable, the clusters then
// coming from the stop's index snapshot; a kill after a later write keeps
// that write.
TEST_F(RestartTest, CleanRestartKeepsTheObservableState) {
  const std::string fleet = "fleet-clean-restart";
  const std::vector<RobotPlan> plans = {{"robot-a", 230}, {"robot-b", 200}};
  for (const RobotPlan& plan : plans) {
    ASSERT_TRUE(UploadTraces(stub(), fleet, MakeTraces(SpecOf(plan))).ok());
  }
  for (int round = 0; round < 3; ++round) {
    ASSERT_TRUE(SampleReplay(stub(), fleet, "robot-b", 60).ok());
  }
  std::vector<v1::QueryPlaceRequest> queries;
  for (uint64_t seq : {1, 50, 100, 150, 200}) {
    v1::QueryPlaceRequest& request = queries.emplace_back();
    request.set_fleet_id(fleet);
    const v1::MemoryTrace trace = MakeTrace(SpecOf(plans[0]), seq);
    for (float value : trace.code()) request.add_code(value);
    request.set_k(20);
  }
  Observation before;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &before));

  ASSERT_NO_FATAL_FAILURE(StopAndRestart());

  Observation after;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &after));
  ExpectSameObservation(before, after, /*with_events=*/true);
  // The stop's snapshot (written after the replay draws) gave the clusters;
  // RocksDB gave none.
  EXPECT_NE(
      server().Output().find("taken from its index snapshot's memory image"),
      std::string::npos)
      << server().Output();

  // A replay draw writes the store after that snapshot, so the restart
  // after a kill must not take the snapshot's clusters (their counts are
  // older): it holds the new counts.
  ASSERT_TRUE(SampleReplay(stub(), fleet, "robot-a", 60).ok());
  Observation drawn;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &drawn));
  ASSERT_NO_FATAL_FAILURE(KillAndRestart());
  Observation killed;
  ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &killed));
  ExpectSameObservation(drawn, killed, /*with_events=*/true);
}

// Descriptors process `pid` holds open on files whose path starts with
// `prefix` (an unlinked file's too: its path then ends in " (deleted)").
int OpenFilesUnder(pid_t pid, const std::string& prefix) {
  int open = 0;
  std::error_code error;
  for (const auto& entry : std::filesystem::directory_iterator(
           "/proc/" + std::to_string(pid) + "/fd", error)) {
    std::error_code unreadable;
    const std::string target =
        std::filesystem::read_symlink(entry.path(), unreadable).string();
    if (!unreadable && target.rfind(prefix, 0) == 0) ++open;
  }
  return open;
}

// Until every code of `fleet` is in its place graph (GetStats'
// unindexed_codes 0): a graph's answers then depend on nothing that
// runs in the background.
void WaitUntilIndexed(v1::MemoryService::Stub& stub, const std::string& fleet) {
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(60);
  for (;;) {
    Reply<v1::GetStatsResponse> stats = GetStats(stub, fleet);
    ASSERT_TRUE(stats.ok()) << Describe(stats.status);
    if (stats.response.unindexed_codes() == 0) return;
    ASSERT_LT(std::chrono::steady_clock::now(), deadline)
        << stats.response.unindexed_codes() << " codes still unindexed";
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
}

// A fleet with a place graph (hnsw_from lowered) keeps its graph's floats
// in its index snapshot's file: a clean start reads them there (the server
// opens no floats' file of its own), uploads after it put their rows in a
// file of the graph's own, and the next stop's snapshot takes them over
// again. Everything a client sees is the same across both restarts.
TEST_F(RestartTest, AGraphReadsItsFloatsFromItsSnapshotAcrossRestarts) {
  ASSERT_NO_FATAL_FAILURE(
      RestartWithConfig("hnsw { hnsw_from: 100 }\n"
                        "index_snapshot_min_codes: 0\n"));
  const std::string fleet = "fleet-graph-floats";
  const std::string floats_files =
      std::filesystem::canonical(data_dir()).string() +
      "/graph-floats/graph-floats-";
  const std::vector<RobotPlan> plans = {
      {"robot-a", 230}, {"robot-b", 200}, {"robot-c", 150}};
  const std::vector<v1::QueryPlaceRequest> queries =
      QueriesOfTheirTraces(fleet, plans);
  for (int round = 0; round < 2; ++round) {
    // Round 1 uploads after a restart: rows of the graph's own.
    const std::vector<RobotPlan> uploaded =
        round == 0 ? std::vector<RobotPlan>{plans[0], plans[1]}
                   : std::vector<RobotPlan>{plans[2]};
    for (const RobotPlan& plan : uploaded) {
      ASSERT_TRUE(UploadTraces(stub(), fleet, MakeTraces(SpecOf(plan))).ok());
    }
    ASSERT_NO_FATAL_FAILURE(WaitUntilIndexed(stub(), fleet));
    if (round == 1) {
      EXPECT_EQ(OpenFilesUnder(server().pid(), floats_files), 1)
          << "the rows written since the start are in no file of their own";
    }
    Observation before;
    ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &before));
    ASSERT_NO_FATAL_FAILURE(StopAndRestart());
    ASSERT_NO_FATAL_FAILURE(WaitUntilIndexed(stub(), fleet));
    EXPECT_EQ(OpenFilesUnder(server().pid(), floats_files), 0)
        << "the restart copied the graph's floats out of its snapshot";
    Observation after;
    ASSERT_NO_FATAL_FAILURE(Observe(fleet, queries, &after));
    ExpectSameObservation(before, after, /*with_events=*/true);
  }
}

// The one index snapshot file under `data_dir` (empty if none or several).
std::string TheSnapshotFile(const std::string& data_dir) {
  std::string found;
  int count = 0;
  for (const auto& entry :
       std::filesystem::recursive_directory_iterator(data_dir)) {
    if (entry.path().extension() == ".snapshot") {
      found = entry.path().string();
      ++count;
    }
  }
  return count == 1 ? found : std::string();
}

// Flips one bit in each row of the self-checked floats of the snapshot at
// `path` (an FMIDXSN2 file: its ranges listed before the trailer); returns
// how many bytes it flipped.
size_t DamageEveryFloatRow(const std::string& path, size_t row_bytes) {
  std::fstream file(path, std::ios::in | std::ios::out | std::ios::binary);
  auto read_at = [&file](std::streamoff at) {
    uint64_t value = 0;
    file.seekg(at);
    file.read(reinterpret_cast<char*>(&value), sizeof(value));
    return value;
  };
  file.seekg(0, std::ios::end);
  const std::streamoff size = file.tellg();
  const uint64_t ranges = read_at(size - 24);
  const uint64_t payload = 16 + 8 + read_at(16);  // after the key
  size_t flipped = 0;
  for (uint64_t i = 0; i < ranges; ++i) {
    const std::streamoff entry = size - 24 - 16 * (ranges - i);
    const uint64_t offset = read_at(entry), length = read_at(entry + 8);
    for (uint64_t row = 0; row + row_bytes <= length; row += row_bytes) {
      const std::streamoff at = payload + offset + row + row_bytes / 2;
      char byte = 0;
      file.seekg(at);
      file.get(byte);
      file.seekp(at);
      file.put(static_cast<char>(byte ^ 0x10));
      ++flipped;
    }
  }
  return file.good() ? flipped : 0;
}

// The floats of a graph's index snapshot are checked row by row when a row
// is read, not when the file is: a start with every row damaged serves,
// a query that rescores a damaged row gets DATA_LOSS (never an answer from
// it), and the next write rebuilds the index from the store's codes, after
// which every query finds its trace and the stop's snapshot is sound.
TEST_F(RestartTest, DamagedFloatsInTheSnapshotAreNeverUsedAndAreRebuilt) {
  ASSERT_NO_FATAL_FAILURE(
      RestartWithConfig("hnsw { hnsw_from: 100 }\n"
                        "index_snapshot_min_codes: 0\n"));
  const std::string fleet = "fleet-damaged-floats";
  const std::vector<RobotPlan> plans = {{"robot-a", 230}, {"robot-b", 200}};
  for (const RobotPlan& plan : plans) {
    ASSERT_TRUE(UploadTraces(stub(), fleet, MakeTraces(SpecOf(plan))).ok());
  }
  ASSERT_NO_FATAL_FAILURE(WaitUntilIndexed(stub(), fleet));
  const std::vector<v1::QueryPlaceRequest> queries =
      QueriesOfTheirTraces(fleet, plans);
  StopServer();
  const std::string snapshot = TheSnapshotFile(data_dir());
  ASSERT_FALSE(snapshot.empty());
  ASSERT_GT(DamageEveryFloatRow(snapshot, (kDim + 1) * sizeof(float)), 0u);
  StartServer();
  // The file's checksum leaves the floats out: the snapshot is used.
  EXPECT_NE(server().Output().find("taken from its index snapshot"),
            std::string::npos);
  Reply<v1::QueryPlaceResponse> damaged = QueryPlace(stub(), queries[0]);
  EXPECT_EQ(damaged.status.error_code(), grpc::StatusCode::DATA_LOSS)
      << Describe(damaged.status);
  EXPECT_NE(damaged.status.error_message().find("fails its checksum"),
            std::string::npos)
      << Describe(damaged.status);

  // A write rebuilds the index from the store.
  ASSERT_TRUE(
      UploadTraces(stub(), fleet, MakeTraces(SpecOf({"robot-c", 150}))).ok());
  ASSERT_NO_FATAL_FAILURE(WaitUntilIndexed(stub(), fleet));
  EXPECT_NE(server().Output().find("rebuilding the index from the store"),
            std::string::npos);
  auto expect_each_finds_itself = [&] {
    for (const v1::QueryPlaceRequest& request : queries) {
      Reply<v1::QueryPlaceResponse> reply = QueryPlace(stub(), request);
      ASSERT_TRUE(reply.ok()) << Describe(reply.status);
      ASSERT_GT(reply.response.matches_size(), 0);
      EXPECT_NEAR(reply.response.matches(0).distance(), 0.0, 1e-4);
    }
  };
  ASSERT_NO_FATAL_FAILURE(expect_each_finds_itself());
  // The stop's snapshot is written from the rebuilt index: sound.
  ASSERT_NO_FATAL_FAILURE(StopAndRestart());
  ASSERT_NO_FATAL_FAILURE(WaitUntilIndexed(stub(), fleet));
  ASSERT_NO_FATAL_FAILURE(expect_each_finds_itself());
}

TEST_F(RestartTest, SigtermDuringUploadExitsCleanlyAndKeepsAcknowledgedData) {
  const std::string fleet = "fleet-shutdown";
  Reply<v1::UploadTracesResponse> acked = UploadTraces(
      stub(), fleet, MakeTraces(SpecOf({"robot-acked", 300})), /*batch=*/100);
  ASSERT_TRUE(acked.ok()) << Describe(acked.status);
  ASSERT_EQ(acked.response.accepted(), 300u);

  // A long upload stream (200 messages of 50 traces) still being written
  // when the server gets SIGTERM.
  constexpr size_t kMessages = 200;
  constexpr size_t kPerMessage = 50;
  const std::vector<v1::MemoryTrace> flight =
      MakeTraces(SpecOf({"robot-flight", kMessages * kPerMessage}));
  std::atomic<size_t> written{0};
  grpc::Status flight_status;
  v1::UploadTracesResponse flight_response;
  std::thread uploader([&] {
    std::unique_ptr<v1::MemoryService::Stub> robot_stub =
        MakeStub(server().address());
    auto context = MakeContext(std::chrono::seconds(120));
    auto writer = robot_stub->UploadTraces(context.get(), &flight_response);
    for (size_t m = 0; m < kMessages; ++m) {
      if (!writer->Write(MakeUploadRequest(
              fleet,
              std::span(flight).subspan(m * kPerMessage, kPerMessage)))) {
        break;
      }
      ++written;
    }
    writer->WritesDone();
    flight_status = writer->Finish();
  });
  // Waits (bounded) until ten messages are on their way.
  for (int i = 0; i < 6000 && written < 10; ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_GE(written.load(), 10u) << "the upload did not get going";

  const size_t written_at_sigterm = written.load();
  absl::StatusOr<int> code = server().Stop(std::chrono::seconds(60));
  uploader.join();
  ASSERT_TRUE(code.ok()) << code.status();
  EXPECT_EQ(*code, 0) << "fleetmem-server did not exit cleanly on SIGTERM";
  EXPECT_TRUE(flight_status.ok() ||
              flight_status.error_code() == grpc::StatusCode::UNAVAILABLE)
      << "in-flight upload ended with " << Describe(flight_status);

  ASSERT_NO_FATAL_FAILURE(StartServer());
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  const v1::RobotStats* robot = FindRobot(stats.response, "robot-acked");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->received(), 300u);
  EXPECT_EQ(robot->max_seq(), 300u);

  // Of the in-flight stream, a prefix of whole messages is stored.
  robot = FindRobot(stats.response, "robot-flight");
  const uint64_t stored = robot == nullptr ? 0 : robot->received();
  std::cout << "in-flight upload: " << written_at_sigterm << " of " << kMessages
            << " messages written at SIGTERM, ended with "
            << Describe(flight_status) << ", " << stored << " of "
            << flight.size() << " traces stored" << std::endl;
  EXPECT_EQ(stored % kPerMessage, 0u) << "a message was stored in part";
  if (robot != nullptr) {
    EXPECT_EQ(robot->max_seq(), stored);
  }
  if (flight_status.ok()) {
    EXPECT_EQ(flight_response.accepted(), flight.size());
    EXPECT_EQ(stored, flight.size());
  }
  if (stored > 0) {
    Reply<v1::UploadTracesResponse> retry = UploadTraces(
        stub(), fleet, std::span(flight).first(stored), /*batch=*/500);
    ASSERT_TRUE(retry.ok()) << Describe(retry.status);
    EXPECT_EQ(retry.response.duplicates(), stored);
    EXPECT_EQ(retry.response.accepted(), 0u);
  }
}

TEST_F(RestartTest, SigtermWithAnIdleClientConnectedExitsCleanly) {
  // Robots stay connected between calls; the server must still stop.
  std::unique_ptr<v1::MemoryService::Stub> robot_stub =
      MakeStub(server().address());
  TraceSpec spec = SpecOf({"robot-idle", 10});
  Reply<v1::UploadTracesResponse> upload =
      UploadTraces(*robot_stub, "fleet-idle-client", MakeTraces(spec));
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  ASSERT_TRUE(GetStats(*robot_stub, "fleet-idle-client").ok());
  // The server cancels idle connections instead of waiting for each
  // client's GOAWAY ping acknowledgement (which a synchronous client gives
  // only from its 5 s backup poller).
  const auto before = std::chrono::steady_clock::now();
  ASSERT_NO_FATAL_FAILURE(StopServer());
  EXPECT_LT(std::chrono::steady_clock::now() - before, std::chrono::seconds(3))
      << "SIGTERM with an idle client connected took too long";
  robot_stub.reset();
  ASSERT_NO_FATAL_FAILURE(StartServer());
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), "fleet-idle-client");
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), 10u);
}

TEST_F(RestartTest, SigtermWithAStalledUploadStreamIsBounded) {
  // A robot sends one message, then its link stalls with the stream open.
  std::unique_ptr<v1::MemoryService::Stub> robot_stub =
      MakeStub(server().address());
  auto context = MakeContext(std::chrono::seconds(120));
  v1::UploadTracesResponse response;
  auto writer = robot_stub->UploadTraces(context.get(), &response);
  TraceSpec spec = SpecOf({"robot-stalled", 10});
  std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
  ASSERT_TRUE(writer->Write(MakeUploadRequest("fleet-stalled", traces)));
  // Wait until the message is durable (visible in the stats).
  bool stored = false;
  for (int i = 0; i < 200 && !stored; ++i) {
    Reply<v1::GetStatsResponse> stats = GetStats(stub(), "fleet-stalled");
    stored = stats.ok() && stats.response.pending_traces() == 10;
    if (!stored) std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  ASSERT_TRUE(stored);
  const auto before = std::chrono::steady_clock::now();
  ASSERT_NO_FATAL_FAILURE(StopServer());
  EXPECT_LT(std::chrono::steady_clock::now() - before, std::chrono::seconds(3))
      << "a stalled upload stream held the shutdown";
  EXPECT_FALSE(writer->Finish().ok());
  ASSERT_NO_FATAL_FAILURE(StartServer());
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), "fleet-stalled");
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), 10u);
}

TEST_F(RestartTest, SigtermWithAnOpenWatchExitsCleanly) {
  const std::string fleet = "fleet-watched";
  ASSERT_TRUE(
      UploadTraces(stub(), fleet, MakeTraces(SpecOf({"robot-w", 40}))).ok());
  Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), fleet);
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  const size_t history = consolidated.response.clusters_added();
  ASSERT_GT(history, 0u);

  std::mutex mu;
  std::condition_variable cv;
  size_t received = 0;
  bool done = false;
  grpc::Status status;
  std::thread watcher([&] {
    std::unique_ptr<v1::MemoryService::Stub> watch_stub =
        MakeStub(server().address());
    auto context = MakeContext(std::chrono::seconds(120));
    v1::WatchMemoryRequest request;
    request.set_fleet_id(fleet);
    auto reader = watch_stub->WatchMemory(context.get(), request);
    v1::MemoryEvent event;
    while (reader->Read(&event)) {
      std::lock_guard<std::mutex> lock(mu);
      ++received;
      cv.notify_all();
    }
    grpc::Status finished = reader->Finish();
    std::lock_guard<std::mutex> lock(mu);
    status = finished;
    done = true;
    cv.notify_all();
  });
  {
    std::unique_lock<std::mutex> lock(mu);
    EXPECT_TRUE(cv.wait_for(lock, std::chrono::seconds(30), [&] {
      return done || received >= history;
    })) << "the watch did not deliver the history";
    EXPECT_FALSE(done) << Describe(status);
  }

  absl::StatusOr<int> code = server().Stop(std::chrono::seconds(30));
  watcher.join();
  ASSERT_TRUE(code.ok()) << code.status()
                         << " (shutdown hangs on an open WatchMemory stream)";
  EXPECT_EQ(*code, 0) << "fleetmem-server did not exit cleanly on SIGTERM";
  // The proto promises UNAVAILABLE while the server shuts down, so that
  // clients reconnect (elsewhere or later) from their cursor.
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAVAILABLE)
      << Describe(status);
  EXPECT_EQ(received, history);

  ASSERT_NO_FATAL_FAILURE(StartServer());
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.clusters(), consolidated.response.clusters());
  EXPECT_EQ(stats.response.traces(), consolidated.response.traces());
}

}  // namespace
}  // namespace fleetmem::testing
