// Integration tests of fleetmem-server's memory API: uploads, consolidation,
// idempotence, concurrency, replay sampling, place queries and the event
// watch. Each test runs against a real server process on a fresh RocksDB
// data directory and uses only the generated fleetmem.v1 stubs.
#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <utility>
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
constexpr uint32_t kSampleAll = 10000;  // max_sample_count

using TraceId = std::pair<std::string, uint64_t>;

TraceId IdOf(const v1::MemoryTrace& trace) {
  return {trace.robot_id(), trace.seq()};
}

// Euclidean distance between the L2-normalised codes.
double NormalisedDistance(const std::vector<float>& a,
                          const std::vector<float>& b) {
  double norm_a = 0, norm_b = 0;
  for (float v : a) norm_a += double{v} * v;
  for (float v : b) norm_b += double{v} * v;
  norm_a = std::sqrt(norm_a);
  norm_b = std::sqrt(norm_b);
  double sum = 0;
  for (size_t i = 0; i < a.size(); ++i) {
    const double d = a[i] / norm_a - b[i] / norm_b;
    sum += d * d;
  }
  return std::sqrt(sum);
}

class MemoryApiTest : public ServerTest {};

TEST_F(MemoryApiTest, UploadThenConsolidate) {
  const std::string fleet = "fleet-basic";
  TraceSpec spec{.robot_id = "robot-1", .count = 50, .dimension = kDim};
  std::vector<v1::MemoryTrace> traces = MakeTraces(spec);

  // A fleet exists only after its first upload.
  EXPECT_EQ(GetStats(stub(), fleet).status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(Consolidate(stub(), fleet).status.error_code(),
            grpc::StatusCode::NOT_FOUND);

  Reply<v1::UploadTracesResponse> upload =
      UploadTraces(stub(), fleet, traces, /*batch=*/20);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 50u);
  EXPECT_EQ(upload.response.duplicates(), 0u);
  EXPECT_EQ(upload.response.consolidations(), 0u);

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), 50u);
  EXPECT_EQ(stats.response.traces(), 0u);
  EXPECT_EQ(stats.response.clusters(), 0u);
  EXPECT_EQ(stats.response.code_dimension(), kDim);
  EXPECT_EQ(stats.response.encoder_version(), "enc-v1");
  EXPECT_EQ(stats.response.last_event_id(), 0u);
  EXPECT_EQ(stats.response.consolidations(), 0u);
  EXPECT_EQ(stats.response.max_clusters(), 100u);
  EXPECT_EQ(stats.response.max_traces_per_cluster(), 50u);
  const v1::RobotStats* robot = FindRobot(stats.response, "robot-1");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->pending_traces(), 50u);
  EXPECT_EQ(robot->traces(), 0u);
  EXPECT_EQ(robot->received(), 50u);
  EXPECT_EQ(robot->max_seq(), 50u);
  EXPECT_EQ(robot->replayed(), 0u);
  ASSERT_EQ(stats.response.domains_size(), 1);
  EXPECT_EQ(stats.response.domains(0).domain(), "summer");
  EXPECT_EQ(stats.response.domains(0).pending_traces(), 50u);

  Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), fleet);
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  const v1::ConsolidateResponse& c = consolidated.response;
  EXPECT_EQ(c.consolidated_traces(), 50u);
  // 50 traces in K = 20 clusters: no cluster can exceed N_max = 50.
  EXPECT_EQ(c.downsampled_traces(), 0u);
  EXPECT_GE(c.clusters_added(), 1u);
  EXPECT_LE(c.clusters_added(), 20u);
  EXPECT_EQ(c.clusters_forgotten(), 0u);
  EXPECT_EQ(c.clusters(), c.clusters_added());
  EXPECT_EQ(c.traces(), 50u);

  stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.traces(), 50u);
  EXPECT_EQ(stats.response.pending_traces(), 0u);
  EXPECT_EQ(stats.response.clusters(), c.clusters());
  EXPECT_EQ(stats.response.consolidations(), 1u);
  EXPECT_EQ(stats.response.clusters_forgotten(), 0u);
  robot = FindRobot(stats.response, "robot-1");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->traces(), 50u);
  EXPECT_EQ(robot->pending_traces(), 0u);
  EXPECT_EQ(robot->received(), 50u);

  // One CLUSTER_ADDED event per new cluster, describing it.
  Reply<std::vector<v1::MemoryEvent>> events =
      ReadEvents(stub(), fleet, 0, stats.response.last_event_id());
  ASSERT_TRUE(events.ok()) << Describe(events.status);
  ASSERT_EQ(events.response.size(), c.clusters_added());
  EXPECT_EQ(stats.response.last_event_id(), events.response.back().id());
  uint64_t traces_in_events = 0;
  std::set<uint64_t> cluster_ids;
  for (const v1::MemoryEvent& event : events.response) {
    EXPECT_EQ(event.type(), v1::MemoryEvent::CLUSTER_ADDED);
    EXPECT_EQ(event.robot_id(), "robot-1");
    EXPECT_EQ(event.domain(), "summer");
    EXPECT_NE(event.cluster_id(), 0u);
    EXPECT_GT(event.trace_count(), 0u);
    EXPECT_GT(event.timestamp_ns(), 0);
    EXPECT_NEAR(event.mean_reward(), 0.5, 1e-6);
    traces_in_events += event.trace_count();
    cluster_ids.insert(event.cluster_id());
  }
  EXPECT_EQ(traces_in_events, 50u);
  EXPECT_EQ(cluster_ids.size(), events.response.size());

  // Nothing pending: a second consolidation adds nothing.
  Reply<v1::ConsolidateResponse> again = Consolidate(stub(), fleet);
  ASSERT_TRUE(again.ok()) << Describe(again.status);
  EXPECT_EQ(again.response.consolidated_traces(), 0u);
  EXPECT_EQ(again.response.clusters_added(), 0u);
  EXPECT_EQ(again.response.clusters(), c.clusters());
  EXPECT_EQ(again.response.traces(), 50u);
}

TEST_F(MemoryApiTest, ConsolidatesAutomaticallyAtSegmentSize) {
  const std::string fleet = "fleet-auto";
  TraceSpec robot1{.robot_id = "robot-1", .count = 200, .dimension = kDim};
  TraceSpec robot2{.robot_id = "robot-2", .count = 150, .dimension = kDim};
  std::vector<v1::MemoryTrace> traces1 = MakeTraces(robot1);
  std::vector<v1::MemoryTrace> traces2 = MakeTraces(robot2);

  // 199 of robot-1 and 150 of robot-2: below the segment size of 200.
  Reply<v1::UploadTracesResponse> upload =
      UploadTraces(stub(), fleet, std::span(traces1).first(199), /*batch=*/100);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 199u);
  EXPECT_EQ(upload.response.consolidations(), 0u);
  upload = UploadTraces(stub(), fleet, traces2, /*batch=*/100);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.consolidations(), 0u);

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), 349u);
  EXPECT_EQ(stats.response.clusters(), 0u);

  // The 200th trace of robot-1 triggers its consolidation, not robot-2's.
  upload = UploadTraces(stub(), fleet, std::span(traces1).last(1));
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 1u);
  EXPECT_EQ(upload.response.consolidations(), 1u);

  stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.consolidations(), 1u);
  EXPECT_EQ(stats.response.pending_traces(), 150u);
  EXPECT_GE(stats.response.clusters(), 1u);
  EXPECT_LE(stats.response.clusters(), 20u);
  EXPECT_GT(stats.response.traces(), 0u);
  EXPECT_LE(stats.response.traces(), 200u);
  const v1::RobotStats* r1 = FindRobot(stats.response, "robot-1");
  const v1::RobotStats* r2 = FindRobot(stats.response, "robot-2");
  ASSERT_NE(r1, nullptr);
  ASSERT_NE(r2, nullptr);
  EXPECT_EQ(r1->pending_traces(), 0u);
  EXPECT_EQ(r1->traces(), stats.response.traces());
  EXPECT_EQ(r1->received(), 200u);
  EXPECT_EQ(r2->pending_traces(), 150u);
  EXPECT_EQ(r2->traces(), 0u);
}

TEST_F(MemoryApiTest, RetriedUploadIsIdempotent) {
  const std::string fleet = "fleet-retry";
  TraceSpec spec{.robot_id = "robot-r", .count = 151, .dimension = kDim};
  std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
  std::span<const v1::MemoryTrace> all(traces);

  Reply<v1::UploadTracesResponse> upload =
      UploadTraces(stub(), fleet, all.first(100), /*batch=*/30);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 100u);
  EXPECT_EQ(upload.response.duplicates(), 0u);

  // The same stream again (a client retrying after a lost response).
  upload = UploadTraces(stub(), fleet, all.first(100), /*batch=*/30);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 0u);
  EXPECT_EQ(upload.response.duplicates(), 100u);
  EXPECT_EQ(upload.response.consolidations(), 0u);

  // Overlapping: 51..150, half of them new.
  upload = UploadTraces(stub(), fleet, all.subspan(50, 100));
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 50u);
  EXPECT_EQ(upload.response.duplicates(), 50u);

  // The identity is (robot_id, seq): a changed payload is still a duplicate.
  v1::MemoryTrace changed = traces[9];
  changed.set_reward(0.99f);
  changed.set_domain("winter");
  upload = UploadTraces(stub(), fleet, std::span(&changed, 1));
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 0u);
  EXPECT_EQ(upload.response.duplicates(), 1u);

  // The same trace twice in one message is stored once.
  std::vector<v1::MemoryTrace> twice = {traces[150], traces[150]};
  upload = UploadTraces(stub(), fleet, twice);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 1u);
  EXPECT_EQ(upload.response.duplicates(), 1u);

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), 151u);
  ASSERT_EQ(stats.response.domains_size(), 1) << "the changed duplicate leaked";
  const v1::RobotStats* robot = FindRobot(stats.response, "robot-r");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->received(), 151u);
  EXPECT_EQ(robot->max_seq(), 151u);

  // After consolidation, every trace is still known, whether it was kept,
  // downsampled or forgotten.
  Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), fleet);
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  EXPECT_EQ(consolidated.response.consolidated_traces(), 151u);
  Reply<v1::GetStatsResponse> before = GetStats(stub(), fleet);
  ASSERT_TRUE(before.ok()) << Describe(before.status);

  upload = UploadTraces(stub(), fleet, all, /*batch=*/50);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  EXPECT_EQ(upload.response.accepted(), 0u);
  EXPECT_EQ(upload.response.duplicates(), 151u);
  EXPECT_EQ(upload.response.consolidations(), 0u);

  Reply<v1::GetStatsResponse> after = GetStats(stub(), fleet);
  ASSERT_TRUE(after.ok()) << Describe(after.status);
  std::string diff;
  MessageDifferencer differencer;
  differencer.ReportDifferencesToString(&diff);
  EXPECT_TRUE(differencer.Compare(before.response, after.response)) << diff;
}

// Every trace of the static memory, drawn by one SampleReplay of
// kSampleAll on behalf of `robot_id` (so every replay count goes up by one).
void SampleEverything(v1::MemoryService::Stub& stub, const std::string& fleet,
                      const std::string& robot_id,
                      std::vector<v1::MemoryTrace>* traces) {
  Reply<v1::SampleReplayResponse> sample =
      SampleReplay(stub, fleet, robot_id, kSampleAll);
  ASSERT_TRUE(sample.ok()) << Describe(sample.status);
  traces->assign(sample.response.traces().begin(),
                 sample.response.traces().end());
}

std::map<uint64_t, std::vector<v1::MemoryTrace>> GroupByCluster(
    const std::vector<v1::MemoryTrace>& traces) {
  std::map<uint64_t, std::vector<v1::MemoryTrace>> clusters;
  for (const v1::MemoryTrace& trace : traces) {
    clusters[trace.cluster_id()].push_back(trace);
  }
  return clusters;
}

TEST_F(MemoryApiTest, ConcurrentRobotsKeepMemoryBounded) {
  const std::string fleet = "fleet-concurrent";
  const std::vector<std::string> robots = {"robot-0", "robot-1", "robot-2",
                                           "robot-3"};
  const std::vector<std::string> domains = {"summer", "winter", "night",
                                            "summer"};
  constexpr size_t kPerRobot = 400;
  constexpr size_t kPerStream = 100;
  constexpr size_t kPerMessage = 50;

  struct RobotOutcome {
    uint64_t accepted = 0;
    uint64_t duplicates = 0;
    uint64_t consolidations = 0;
    uint64_t retries = 0;
    std::vector<std::string> errors;
  };
  std::vector<RobotOutcome> outcomes(robots.size());
  std::vector<std::thread> threads;
  for (size_t k = 0; k < robots.size(); ++k) {
    threads.emplace_back([&, k] {
      // Each robot has its own channel, as separate machines would.
      std::unique_ptr<v1::MemoryService::Stub> robot_stub =
          MakeStub(server().address());
      TraceSpec spec{
          .robot_id = robots[k],
          .count = kPerRobot,
          .dimension = kDim,
          .domain = domains[k],
          .reward = [](uint64_t seq) { return 0.1f + 0.2f * (seq % 5); },
          .seed = 7};
      std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
      RobotOutcome& outcome = outcomes[k];
      for (size_t s = 0; s < kPerRobot / kPerStream; ++s) {
        std::span<const v1::MemoryTrace> part =
            std::span(traces).subspan(s * kPerStream, kPerStream);
        // Every other stream is sent twice, as after a lost response.
        const int attempts = (s + k) % 2 == 0 ? 2 : 1;
        for (int attempt = 0; attempt < attempts; ++attempt) {
          Reply<v1::UploadTracesResponse> reply =
              UploadTraces(*robot_stub, fleet, part, kPerMessage);
          if (!reply.ok()) {
            outcome.errors.push_back(Describe(reply.status));
            continue;
          }
          if (attempt > 0) {
            ++outcome.retries;
            if (reply.response.accepted() != 0 ||
                reply.response.duplicates() != kPerStream) {
              outcome.errors.push_back("retry was not all duplicates: " +
                                       reply.response.ShortDebugString());
            }
          }
          outcome.accepted += reply.response.accepted();
          outcome.duplicates += reply.response.duplicates();
          outcome.consolidations += reply.response.consolidations();
        }
      }
    });
  }
  for (std::thread& thread : threads) thread.join();

  uint64_t accepted = 0, duplicates = 0, consolidations = 0, retries = 0;
  for (size_t k = 0; k < robots.size(); ++k) {
    EXPECT_TRUE(outcomes[k].errors.empty())
        << robots[k] << ": " << outcomes[k].errors.front();
    EXPECT_EQ(outcomes[k].accepted, kPerRobot) << robots[k];
    accepted += outcomes[k].accepted;
    duplicates += outcomes[k].duplicates;
    consolidations += outcomes[k].consolidations;
    retries += outcomes[k].retries;
  }
  EXPECT_EQ(retries, 8u);
  EXPECT_EQ(accepted, robots.size() * kPerRobot);
  EXPECT_EQ(duplicates, retries * kPerStream);
  // Each robot reached the segment size twice.
  EXPECT_EQ(consolidations, 2 * robots.size());

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  const v1::GetStatsResponse& s = stats.response;
  EXPECT_EQ(s.consolidations(), consolidations);
  EXPECT_EQ(s.pending_traces(), 0u);
  EXPECT_LE(s.clusters(), 100u) << "K_max exceeded";
  EXPECT_GE(s.clusters(), 1u);
  EXPECT_LE(s.traces(), robots.size() * kPerRobot);
  uint64_t robot_traces = 0, received = 0;
  for (size_t k = 0; k < robots.size(); ++k) {
    const v1::RobotStats* robot = FindRobot(s, robots[k]);
    ASSERT_NE(robot, nullptr) << robots[k];
    EXPECT_EQ(robot->received(), kPerRobot);
    EXPECT_EQ(robot->max_seq(), kPerRobot);
    EXPECT_EQ(robot->pending_traces(), 0u);
    robot_traces += robot->traces();
    received += robot->received();
  }
  EXPECT_EQ(robot_traces, s.traces());
  EXPECT_EQ(received, accepted);
  uint64_t domain_traces = 0;
  for (const v1::DomainStats& domain : s.domains()) {
    domain_traces += domain.traces();
  }
  EXPECT_EQ(domain_traces, s.traces());

  // The event history accounts for every cluster: added - forgotten.
  Reply<std::vector<v1::MemoryEvent>> events =
      ReadEvents(stub(), fleet, 0, s.last_event_id());
  ASSERT_TRUE(events.ok()) << Describe(events.status);
  uint64_t added = 0, forgotten = 0, previous_id = 0;
  int64_t traces_in_events = 0;
  std::set<uint64_t> live_clusters;
  for (const v1::MemoryEvent& event : events.response) {
    EXPECT_GT(event.id(), previous_id);
    previous_id = event.id();
    if (event.type() == v1::MemoryEvent::CLUSTER_ADDED) {
      ++added;
      traces_in_events += event.trace_count();
      EXPECT_TRUE(live_clusters.insert(event.cluster_id()).second);
      EXPECT_LE(event.trace_count(), 50u);
    } else if (event.type() == v1::MemoryEvent::CLUSTER_FORGOTTEN) {
      ++forgotten;
      traces_in_events -= event.trace_count();
      EXPECT_EQ(live_clusters.erase(event.cluster_id()), 1u)
          << "forgotten cluster " << event.cluster_id() << " was not live";
    } else if (event.type() == v1::MemoryEvent::CLUSTER_MERGED) {
      // The server's default forgetting: the traces live on in the
      // survivor but for those the merge dropped.
      ++forgotten;
      traces_in_events -= event.traces_dropped();
      EXPECT_EQ(live_clusters.erase(event.cluster_id()), 1u)
          << "merged cluster " << event.cluster_id() << " was not live";
      EXPECT_TRUE(live_clusters.contains(event.merged_into()))
          << "merged into " << event.merged_into() << ", not live";
    } else {
      ADD_FAILURE() << "event of unknown type: " << event.ShortDebugString();
    }
  }
  EXPECT_EQ(previous_id, s.last_event_id());
  EXPECT_EQ(added - forgotten, s.clusters());
  EXPECT_EQ(forgotten, s.clusters_forgotten());
  EXPECT_EQ(traces_in_events, static_cast<int64_t>(s.traces()));
  // Eight segments of 200 made more than K_max clusters; forgetting keeps
  // exactly K_max (Algorithm 2 removes only while there are too many).
  EXPECT_GT(added, 100u) << "precondition: enough clusters to forget some";
  EXPECT_EQ(s.clusters(), std::min<uint64_t>(added, 100));
  EXPECT_GT(s.clusters_forgotten(), 0u);

  // Every cluster holds at most N_max = 50 traces.
  std::vector<v1::MemoryTrace> stored;
  ASSERT_NO_FATAL_FAILURE(SampleEverything(stub(), fleet, "robot-0", &stored));
  EXPECT_EQ(stored.size(), s.traces());
  std::map<uint64_t, std::vector<v1::MemoryTrace>> clusters =
      GroupByCluster(stored);
  EXPECT_EQ(clusters.size(), s.clusters());
  std::set<uint64_t> sampled_cluster_ids;
  for (const auto& [cluster_id, members] : clusters) {
    EXPECT_NE(cluster_id, 0u) << "a stored trace without a cluster";
    EXPECT_LE(members.size(), 50u) << "cluster " << cluster_id;
    sampled_cluster_ids.insert(cluster_id);
  }
  EXPECT_EQ(sampled_cluster_ids, live_clusters);
}

TEST_F(MemoryApiTest, DownsamplingBoundsClustersAndKeepsHighRewards) {
  // A robot standing still at two places: 95 identical traces at each, with
  // distinct rewards. Clusters must still hold at most N_max = 50 traces,
  // and (memory.md) downsampling keeps the highest rewards.
  const std::string fleet = "fleet-downsample";
  std::vector<v1::MemoryTrace> traces;
  for (uint64_t seq = 1; seq <= 190; ++seq) {
    TraceSpec spec{.robot_id = "robot-still", .dimension = kDim};
    const uint64_t place = seq % 2;
    v1::MemoryTrace trace = MakeTrace(spec, 1000 + place);
    trace.set_seq(seq);
    trace.set_reward(static_cast<float>(seq) / 1000.0f);
    traces.push_back(trace);
  }
  Reply<v1::UploadTracesResponse> upload =
      UploadTraces(stub(), fleet, traces, /*batch=*/100);
  ASSERT_TRUE(upload.ok()) << Describe(upload.status);
  ASSERT_EQ(upload.response.accepted(), 190u);

  Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), fleet);
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  const v1::ConsolidateResponse& c = consolidated.response;
  EXPECT_EQ(c.consolidated_traces(), 190u);
  EXPECT_EQ(c.traces() + c.downsampled_traces(), 190u);
  // Each place lands in at least one cluster, which keeps up to 50.
  EXPECT_GE(c.traces(), 100u);

  std::vector<v1::MemoryTrace> stored;
  ASSERT_NO_FATAL_FAILURE(
      SampleEverything(stub(), fleet, "robot-still", &stored));
  EXPECT_EQ(stored.size(), c.traces());
  for (const auto& [cluster_id, members] : GroupByCluster(stored)) {
    EXPECT_LE(members.size(), 50u) << "cluster " << cluster_id;
  }
  // Where a place kept exactly 50 of its 95 traces (one cluster), they are
  // its 50 highest rewards.
  for (uint64_t place = 0; place < 2; ++place) {
    std::vector<uint64_t> kept;
    for (const v1::MemoryTrace& trace : stored) {
      if (trace.seq() % 2 == place) kept.push_back(trace.seq());
    }
    std::sort(kept.begin(), kept.end());
    if (kept.size() != 50) continue;
    std::vector<uint64_t> top;
    for (uint64_t seq = 190; top.size() < 50; --seq) {
      if (seq % 2 == place) top.push_back(seq);
    }
    std::sort(top.begin(), top.end());
    EXPECT_EQ(kept, top) << "place " << place;
  }
}

TEST_F(MemoryApiTest, SampleReplayReturnsDistinctTracesAndCountsReplays) {
  const std::string fleet = "fleet-sample";
  for (const std::string robot : {"robot-a", "robot-b"}) {
    TraceSpec spec{.robot_id = robot, .count = 60, .dimension = kDim};
    std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
    ASSERT_TRUE(UploadTraces(stub(), fleet, traces).ok());
  }
  EXPECT_EQ(
      SampleReplay(stub(), "no-such-fleet", "robot-a", 1).status.error_code(),
      grpc::StatusCode::NOT_FOUND);
  // Pending traces are not in the static memory yet.
  Reply<v1::SampleReplayResponse> none =
      SampleReplay(stub(), fleet, "robot-a", 10);
  ASSERT_TRUE(none.ok()) << Describe(none.status);
  EXPECT_EQ(none.response.traces_size(), 0);

  Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), fleet);
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  const uint64_t stored = consolidated.response.traces();
  ASSERT_GT(stored, 20u);
  // Five more, left pending: never sampled.
  TraceSpec extra{
      .robot_id = "robot-a", .first_seq = 61, .count = 5, .dimension = kDim};
  ASSERT_TRUE(UploadTraces(stub(), fleet, MakeTraces(extra)).ok());

  // Asking for more than there is returns each stored trace once.
  Reply<v1::SampleReplayResponse> all =
      SampleReplay(stub(), fleet, "robot-a", 1000);
  ASSERT_TRUE(all.ok()) << Describe(all.status);
  EXPECT_EQ(static_cast<uint64_t>(all.response.traces_size()), stored);
  std::set<TraceId> ids;
  for (const v1::MemoryTrace& trace : all.response.traces()) {
    EXPECT_TRUE(ids.insert(IdOf(trace)).second)
        << "drawn twice: " << trace.robot_id() << "/" << trace.seq();
    EXPECT_EQ(trace.replay_count(), 1u);
    EXPECT_NE(trace.cluster_id(), 0u);
    EXPECT_LE(trace.seq(), 60u) << "a pending trace was sampled";
    EXPECT_EQ(trace.code_size(), static_cast<int>(kDim));
    EXPECT_EQ(trace.encoder_version(), "enc-v1");
  }

  Reply<v1::SampleReplayResponse> ten =
      SampleReplay(stub(), fleet, "robot-b", 10);
  ASSERT_TRUE(ten.ok()) << Describe(ten.status);
  ASSERT_EQ(ten.response.traces_size(), 10);
  std::set<TraceId> ten_ids;
  for (const v1::MemoryTrace& trace : ten.response.traces()) {
    EXPECT_TRUE(ten_ids.insert(IdOf(trace)).second);
    EXPECT_EQ(trace.replay_count(), 2u);
  }

  Reply<v1::SampleReplayResponse> again =
      SampleReplay(stub(), fleet, "robot-b", kSampleAll);
  ASSERT_TRUE(again.ok()) << Describe(again.status);
  EXPECT_EQ(static_cast<uint64_t>(again.response.traces_size()), stored);
  for (const v1::MemoryTrace& trace : again.response.traces()) {
    EXPECT_EQ(trace.replay_count(), ten_ids.contains(IdOf(trace)) ? 3u : 2u)
        << trace.robot_id() << "/" << trace.seq();
  }

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  const v1::RobotStats* a = FindRobot(stats.response, "robot-a");
  const v1::RobotStats* b = FindRobot(stats.response, "robot-b");
  ASSERT_NE(a, nullptr);
  ASSERT_NE(b, nullptr);
  EXPECT_EQ(a->replayed(), stored);
  EXPECT_EQ(b->replayed(), 10 + stored);
}

TEST_F(MemoryApiTest, SampleReplayFavoursHighRewards) {
  // 1,000 stored traces (5 segments of 200 = 100 clusters = K_max, nothing
  // downsampled or forgotten), half with reward 1.0 and half with 0.1.
  const std::string fleet = "fleet-rewards";
  for (int r = 0; r < 5; ++r) {
    TraceSpec spec{
        .robot_id = "robot-" + std::to_string(r),
        .count = 200,
        .dimension = kDim,
        .reward = [](uint64_t seq) { return seq % 2 == 0 ? 1.0f : 0.1f; }};
    Reply<v1::UploadTracesResponse> upload =
        UploadTraces(stub(), fleet, MakeTraces(spec));
    ASSERT_TRUE(upload.ok()) << Describe(upload.status);
    ASSERT_EQ(upload.response.consolidations(), 1u);
  }
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), fleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  ASSERT_EQ(stats.response.traces(), 1000u)
      << "precondition: nothing downsampled or forgotten";

  // Ten refreshes of 10% each. Eq. 18 bound: in round r (0..9) every trace
  // has n <= r, so a high trace weighs >= 0.9^r and a low one <= 0.1; while
  // drawing a round, >= 400 high and <= 500 low traces remain, so every draw
  // is high with probability >= 400*0.9^r / (400*0.9^r + 50): 0.889 in round
  // 0 .. 0.756 in round 9, 0.829 on average. Over 1,000 draws the share falls
  // below 0.75 with probability < exp(-2 * 1000 * 0.079^2) ~ 4e-6 (Azuma).
  // Uniform sampling would give 0.5.
  size_t high = 0, drawn = 0;
  for (int round = 0; round < 10; ++round) {
    Reply<v1::SampleReplayResponse> sample =
        SampleReplay(stub(), fleet, "robot-0", 100);
    ASSERT_TRUE(sample.ok()) << Describe(sample.status);
    ASSERT_EQ(sample.response.traces_size(), 100);
    std::set<TraceId> ids;
    for (const v1::MemoryTrace& trace : sample.response.traces()) {
      EXPECT_TRUE(ids.insert(IdOf(trace)).second);
      high += trace.reward() > 0.5f ? 1 : 0;
      ++drawn;
    }
  }
  const double share = static_cast<double>(high) / drawn;
  EXPECT_GT(share, 0.75) << high << " of " << drawn
                         << " draws had the high reward";
}

class QueryPlaceTest : public ServerTest {
 protected:
  // 100 traces of robot-q, 5 m apart along x, consolidated (nothing
  // downsampled: K = 20 clusters of ~5 traces along the route).
  void SetUp() override {
    ASSERT_NO_FATAL_FAILURE(ServerTest::SetUp());
    traces_ = MakeTraces(spec_);
    ASSERT_TRUE(UploadTraces(stub(), kFleet, traces_).ok());
    Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), kFleet);
    ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
    ASSERT_EQ(consolidated.response.traces(), 100u) << "precondition";
  }

  const v1::MemoryTrace& trace(uint64_t seq) const { return traces_[seq - 1]; }

  static constexpr char kFleet[] = "fleet-query";
  TraceSpec spec_{.robot_id = "robot-q",
                  .count = 100,
                  .dimension = kDim,
                  .domain = "night",
                  .step_m = 5.0};
  std::vector<v1::MemoryTrace> traces_;
};

TEST_F(QueryPlaceTest, StoredCodeFindsItselfFirst) {
  for (uint64_t seq : {1, 37, 64, 100}) {
    Reply<v1::QueryPlaceResponse> reply =
        QueryCode(stub(), kFleet, CodeOf(trace(seq)), 5);
    ASSERT_TRUE(reply.ok()) << Describe(reply.status);
    ASSERT_EQ(reply.response.matches_size(), 5) << "seq " << seq;
    const v1::PlaceMatch& first = reply.response.matches(0);
    EXPECT_EQ(first.trace().robot_id(), "robot-q");
    EXPECT_EQ(first.trace().seq(), seq);
    EXPECT_NEAR(first.distance(), 0.0, 1e-4);
    EXPECT_EQ(first.trace().domain(), "night");
    EXPECT_NEAR(first.trace().pose().x(), trace(seq).pose().x(), 1e-9);
    EXPECT_NEAR(first.trace().pose().y(), trace(seq).pose().y(), 1e-9);
    EXPECT_FLOAT_EQ(first.trace().reward(), trace(seq).reward());
    EXPECT_NE(first.trace().cluster_id(), 0u);
    EXPECT_EQ(CodeOf(first.trace()), CodeOf(trace(seq)));
    std::set<uint64_t> seen;
    float previous = -1.0f;
    for (const v1::PlaceMatch& match : reply.response.matches()) {
      EXPECT_GE(match.distance(), previous) << "not nearest first";
      previous = match.distance();
      EXPECT_LE(match.distance(), 2.0f + 1e-5f);
      EXPECT_TRUE(seen.insert(match.trace().seq()).second);
      // The distance is between the L2-normalised codes.
      EXPECT_NEAR(match.distance(),
                  NormalisedDistance(CodeOf(trace(seq)),
                                     CodeOf(trace(match.trace().seq()))),
                  1e-4);
    }
  }
}

TEST_F(QueryPlaceTest, CodesAreComparedAfterNormalisation) {
  std::vector<float> scaled = CodeOf(trace(42));
  for (float& value : scaled) value *= 3.5f;
  Reply<v1::QueryPlaceResponse> reply = QueryCode(stub(), kFleet, scaled, 1);
  ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  ASSERT_EQ(reply.response.matches_size(), 1);
  EXPECT_EQ(reply.response.matches(0).trace().seq(), 42u);
  EXPECT_NEAR(reply.response.matches(0).distance(), 0.0, 1e-4);
}

TEST_F(QueryPlaceTest, MatchesTheExactNeighbours) {
  // Exact search is the reference; the server's index must find (nearly)
  // the same ten neighbours for codes that are not stored.
  size_t found = 0, wanted = 0;
  for (uint64_t q = 0; q < 10; ++q) {
    std::vector<float> query = RandomCode(99, "query", q, kDim);
    std::vector<std::pair<double, uint64_t>> exact;
    for (const v1::MemoryTrace& t : traces_) {
      exact.emplace_back(NormalisedDistance(query, CodeOf(t)), t.seq());
    }
    std::sort(exact.begin(), exact.end());
    std::set<uint64_t> expected;
    for (size_t i = 0; i < 10; ++i) expected.insert(exact[i].second);
    Reply<v1::QueryPlaceResponse> reply = QueryCode(stub(), kFleet, query, 10);
    ASSERT_TRUE(reply.ok()) << Describe(reply.status);
    ASSERT_EQ(reply.response.matches_size(), 10);
    EXPECT_NEAR(reply.response.matches(0).distance(), exact[0].first, 1e-4);
    for (const v1::PlaceMatch& match : reply.response.matches()) {
      found += expected.contains(match.trace().seq()) ? 1 : 0;
    }
    wanted += 10;
  }
  EXPECT_GE(static_cast<double>(found) / wanted, 0.9)
      << found << " of " << wanted << " exact neighbours found";
}

TEST_F(QueryPlaceTest, KLimitsTheMatches) {
  const std::vector<float> code = CodeOf(trace(10));
  struct Case {
    uint32_t k;
    int expected;
  };
  for (Case c :
       {Case{0, 1}, Case{1, 1}, Case{7, 7}, Case{100, 100}, Case{1000, 100}}) {
    Reply<v1::QueryPlaceResponse> reply = QueryCode(stub(), kFleet, code, c.k);
    ASSERT_TRUE(reply.ok()) << "k=" << c.k << ": " << Describe(reply.status);
    EXPECT_EQ(reply.response.matches_size(), c.expected) << "k=" << c.k;
  }
}

TEST_F(QueryPlaceTest, PositionPriorLimitsTheRadius) {
  // Near trace 50 (x = 250 m) within 12 m: traces 48..52 (x = 240..260 m).
  v1::QueryPlaceRequest request;
  request.set_fleet_id(kFleet);
  for (float value : CodeOf(trace(1))) request.add_code(value);
  request.set_k(100);
  *request.mutable_near() = trace(50).pose();
  request.set_radius_m(12.0);
  Reply<v1::QueryPlaceResponse> reply = QueryPlace(stub(), request);
  ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  std::set<uint64_t> seqs;
  size_t outside = 0;
  for (const v1::PlaceMatch& match : reply.response.matches()) {
    seqs.insert(match.trace().seq());
    const double dx = match.trace().pose().x() - trace(50).pose().x();
    const double dy = match.trace().pose().y() - trace(50).pose().y();
    outside += std::sqrt(dx * dx + dy * dy) > 12.0 + 1e-9 ? 1 : 0;
  }
  EXPECT_EQ(outside, 0u) << "of " << reply.response.matches_size()
                         << " matches, outside the 12 m radius";
  EXPECT_EQ(seqs, (std::set<uint64_t>{48, 49, 50, 51, 52}));

  // Nothing within the radius: an empty answer, not an error.
  request.mutable_near()->set_x(-10000.0);
  reply = QueryPlace(stub(), request);
  ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  EXPECT_EQ(reply.response.matches_size(), 0);

  // radius_m <= 0: the prior is ignored.
  request.set_radius_m(0.0);
  request.set_k(1);
  reply = QueryPlace(stub(), request);
  ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  ASSERT_EQ(reply.response.matches_size(), 1);
  EXPECT_EQ(reply.response.matches(0).trace().seq(), 1u);
}

TEST_F(QueryPlaceTest, PendingTracesAreMatchedBeforeConsolidation) {
  TraceSpec pending = spec_;
  pending.first_seq = 101;
  pending.count = 1;
  std::vector<v1::MemoryTrace> extra = MakeTraces(pending);
  ASSERT_TRUE(UploadTraces(stub(), kFleet, extra).ok());
  Reply<v1::QueryPlaceResponse> reply =
      QueryCode(stub(), kFleet, CodeOf(extra[0]), 1000);
  ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  EXPECT_EQ(reply.response.matches_size(), 101);
  ASSERT_GT(reply.response.matches_size(), 0);
  // The just-uploaded trace finds itself first and says it is pending.
  const v1::PlaceMatch& first = reply.response.matches(0);
  EXPECT_EQ(first.trace().seq(), 101u);
  EXPECT_EQ(first.trace().cluster_id(), 0u);
  EXPECT_NEAR(first.distance(), 0.0f, 1e-4f);
  EXPECT_EQ(QueryCode(stub(), "no-such-fleet", CodeOf(extra[0]), 1)
                .status.error_code(),
            grpc::StatusCode::NOT_FOUND);
}

class WatchMemoryTest : public ServerTest {
 protected:
  // Three consolidations of 60 traces: ~60 CLUSTER_ADDED events.
  void SetUp() override {
    ASSERT_NO_FATAL_FAILURE(ServerTest::SetUp());
    for (int part = 0; part < 3; ++part) {
      TraceSpec spec{.robot_id = "robot-w",
                     .first_seq = 1 + 60 * static_cast<uint64_t>(part),
                     .count = 60,
                     .dimension = kDim};
      ASSERT_TRUE(UploadTraces(stub(), kFleet, MakeTraces(spec)).ok());
      ASSERT_TRUE(Consolidate(stub(), kFleet).ok());
    }
    Reply<v1::GetStatsResponse> stats = GetStats(stub(), kFleet);
    ASSERT_TRUE(stats.ok()) << Describe(stats.status);
    stats_ = stats.response;
    ASSERT_GE(stats_.last_event_id(), 30u) << "precondition";
    Reply<std::vector<v1::MemoryEvent>> all =
        ReadEvents(stub(), kFleet, 0, stats_.last_event_id());
    ASSERT_TRUE(all.ok()) << Describe(all.status);
    all_ = all.response;
  }

  static constexpr char kFleet[] = "fleet-watch";
  v1::GetStatsResponse stats_;
  std::vector<v1::MemoryEvent> all_;
};

void ExpectSameEvents(const std::vector<v1::MemoryEvent>& actual,
                      std::span<const v1::MemoryEvent> expected) {
  ASSERT_EQ(actual.size(), expected.size());
  for (size_t i = 0; i < actual.size(); ++i) {
    EXPECT_TRUE(MessageDifferencer::Equals(actual[i], expected[i]))
        << "event " << i << ": " << actual[i].ShortDebugString() << " vs "
        << expected[i].ShortDebugString();
  }
}

TEST_F(WatchMemoryTest, HistoryHasIncreasingIdsFromOne) {
  ASSERT_FALSE(all_.empty());
  EXPECT_EQ(all_.front().id(), 1u);
  EXPECT_EQ(all_.back().id(), stats_.last_event_id());
  uint64_t traces = 0;
  for (size_t i = 1; i < all_.size(); ++i) {
    EXPECT_GT(all_[i].id(), all_[i - 1].id());
  }
  for (const v1::MemoryEvent& event : all_) {
    EXPECT_EQ(event.type(), v1::MemoryEvent::CLUSTER_ADDED);
    EXPECT_EQ(event.robot_id(), "robot-w");
    traces += event.trace_count();
  }
  EXPECT_EQ(all_.size(), stats_.clusters());
  EXPECT_EQ(traces, stats_.traces());
}

TEST_F(WatchMemoryTest, ResumeAfterDisconnectMissesAndRepeatsNothing) {
  // Disconnect after seven events, resume from the last one received.
  Reply<std::vector<v1::MemoryEvent>> first =
      ReadEvents(stub(), kFleet, 0, /*until_event=*/0, /*max_events=*/7);
  ASSERT_TRUE(first.ok()) << Describe(first.status);
  ASSERT_NO_FATAL_FAILURE(
      ExpectSameEvents(first.response, std::span(all_).first(7)));
  Reply<std::vector<v1::MemoryEvent>> rest = ReadEvents(
      stub(), kFleet, first.response.back().id(), stats_.last_event_id());
  ASSERT_TRUE(rest.ok()) << Describe(rest.status);
  ASSERT_NO_FATAL_FAILURE(
      ExpectSameEvents(rest.response, std::span(all_).subspan(7)));

  // Any cursor works, also one in the middle.
  const size_t middle = all_.size() / 2;
  Reply<std::vector<v1::MemoryEvent>> tail =
      ReadEvents(stub(), kFleet, all_[middle].id(), stats_.last_event_id());
  ASSERT_TRUE(tail.ok()) << Describe(tail.status);
  ASSERT_NO_FATAL_FAILURE(
      ExpectSameEvents(tail.response, std::span(all_).subspan(middle + 1)));
}

TEST_F(WatchMemoryTest, LiveEventsArriveWhileWatching) {
  std::mutex mu;
  std::condition_variable cv;
  std::vector<v1::MemoryEvent> received;
  bool done = false;
  grpc::Status status;
  std::unique_ptr<grpc::ClientContext> context =
      MakeContext(std::chrono::seconds(60));
  v1::WatchMemoryRequest request;
  request.set_fleet_id(kFleet);
  request.set_after_event(stats_.last_event_id());
  std::thread watcher([&] {
    auto reader = stub().WatchMemory(context.get(), request);
    v1::MemoryEvent event;
    while (reader->Read(&event)) {
      std::lock_guard<std::mutex> lock(mu);
      received.push_back(event);
      cv.notify_all();
    }
    grpc::Status finished = reader->Finish();
    std::lock_guard<std::mutex> lock(mu);
    status = finished;
    done = true;
    cv.notify_all();
  });
  // Waits (bounded) until an event with id >= `id` arrived; false if the
  // stream ended or nothing came within 30 s.
  auto wait_for_event = [&](uint64_t id) {
    std::unique_lock<std::mutex> lock(mu);
    return cv.wait_for(lock, std::chrono::seconds(30), [&] {
      return done || (!received.empty() && received.back().id() >= id);
    }) && !done;
  };

  // Two segments of another robot, consolidated one after the other. The
  // second surely happens after the watch is established.
  uint64_t expected_last = stats_.last_event_id();
  for (int part = 0; part < 2; ++part) {
    TraceSpec spec{.robot_id = "robot-live",
                   .first_seq = 1 + 40 * static_cast<uint64_t>(part),
                   .count = 40,
                   .dimension = kDim,
                   .domain = "winter"};
    ASSERT_TRUE(UploadTraces(stub(), kFleet, MakeTraces(spec)).ok());
    Reply<v1::ConsolidateResponse> consolidated = Consolidate(stub(), kFleet);
    ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
    expected_last += consolidated.response.clusters_added() +
                     consolidated.response.clusters_forgotten();
    const bool arrived = wait_for_event(expected_last);
    EXPECT_TRUE(arrived) << "live events of part " << part << " not received";
    if (!arrived) break;
  }
  context->TryCancel();
  watcher.join();

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), kFleet);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats.response.last_event_id(), expected_last);
  std::lock_guard<std::mutex> lock(mu);
  ASSERT_FALSE(received.empty()) << Describe(status);
  uint64_t previous = stats_.last_event_id();
  for (const v1::MemoryEvent& event : received) {
    EXPECT_GT(event.id(), previous) << "repeated or out of order";
    previous = event.id();
    EXPECT_EQ(event.robot_id(), "robot-live");
    EXPECT_EQ(event.domain(), "winter");
  }
  EXPECT_EQ(received.back().id(), expected_last);
  // None missed: the live stream equals the history read afterwards.
  Reply<std::vector<v1::MemoryEvent>> history =
      ReadEvents(stub(), kFleet, stats_.last_event_id(), expected_last);
  ASSERT_TRUE(history.ok()) << Describe(history.status);
  ExpectSameEvents(received, history.response);
}

}  // namespace
}  // namespace fleetmem::testing
