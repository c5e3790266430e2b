// Quotas and event retention against the real server: every refusal is
// RESOURCE_EXHAUSTED naming its limit, changes nothing and is counted; a
// watcher whose cursor was compacted away gets OUT_OF_RANGE.
#include <chrono>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "grpcpp/grpcpp.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
#include "tests/server_process.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

constexpr char kFleet[] = "limited";

class LimitsTest : public ::testing::Test {
 protected:
  void Start(const std::string& config_text) {
    const std::string config = dir_.Join("server.textproto");
    std::ofstream(config) << config_text;
    ServerOptions options;
    options.data_dir = dir_.Join("data");
    options.config_file = config;
    options.log_file = dir_.Join("server.log");
    server_ = std::make_unique<ServerProcess>(options);
    absl::Status started = server_->Start();
    ASSERT_TRUE(started.ok()) << started;
    stub_ = MakeStub(server_->address());
  }

  void TearDown() override {
    stub_.reset();
    if (server_ != nullptr && server_->running()) {
      absl::StatusOr<int> code = server_->Stop();
      EXPECT_TRUE(code.ok() && *code == 0);
    }
    if (HasFailure() && server_ != nullptr) std::cerr << server_->Output();
  }

  static void ExpectLimit(const grpc::Status& status, const std::string& name) {
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED)
        << Describe(status);
    EXPECT_TRUE(absl::StrContains(status.error_message(), "limit " + name))
        << Describe(status);
  }

  TempDir dir_{"fleetmem-limits-"};
  std::unique_ptr<ServerProcess> server_;
  std::unique_ptr<v1::MemoryService::Stub> stub_;
};

TEST_F(LimitsTest, QuotasRefuseNameTheLimitAndAreCounted) {
  ASSERT_NO_FATAL_FAILURE(Start(
      "limits { robot_traces_per_second: 1 burst_seconds: 100 max_fleets: 1 "
      "max_code_dimension: 64 }\n"));
  TraceSpec spec{.robot_id = "r1", .count = 100, .dimension = 32};
  ASSERT_TRUE(UploadTraces(*stub_, kFleet, MakeTraces(spec)).ok());
  // The bucket (100 traces) is empty now.
  spec.first_seq = 101;
  spec.count = 10;
  Reply<v1::UploadTracesResponse> refused =
      UploadTraces(*stub_, kFleet, MakeTraces(spec));
  ExpectLimit(refused.status, "robot_traces_per_second");
  // Another fleet would exceed max_fleets; a wide code max_code_dimension.
  ExpectLimit(UploadTraces(*stub_, "other", MakeTraces(spec)).status,
              "max_fleets");
  Reply<v1::GetStatsResponse> stats = GetStats(*stub_, kFleet);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(), 100u);
  EXPECT_EQ(stats.response.quota_rejections().at("robot_traces_per_second"),
            1u);
  EXPECT_EQ(GetStats(*stub_, "other").status.error_code(),
            grpc::StatusCode::NOT_FOUND);
}

// With auto_create_fleets off, an upload to a fleet that does not exist is
// refused (NOT_FOUND, nothing stored) until CreateFleet makes it; the
// fleet then takes its uploads, and a second CreateFleet is ALREADY_EXISTS.
TEST_F(LimitsTest, FleetsMadeByCreateFleetOnly) {
  ASSERT_NO_FATAL_FAILURE(Start("limits { auto_create_fleets: false }\n"));
  TraceSpec spec{.robot_id = "r1", .count = 30, .dimension = 8};
  Reply<v1::UploadTracesResponse> refused =
      UploadTraces(*stub_, kFleet, MakeTraces(spec));
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::NOT_FOUND)
      << Describe(refused.status);
  EXPECT_TRUE(
      absl::StrContains(refused.status.error_message(), "auto_create_fleets"));
  EXPECT_EQ(GetStats(*stub_, kFleet).status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  v1::CreateFleetRequest create;
  create.set_fleet_id(kFleet);
  create.mutable_settings()->set_code_dimension(8);
  create.mutable_settings()->set_encoder_version(
      MakeTraces(spec)[0].encoder_version());
  create.mutable_settings()->set_max_clusters(3);
  v1::CreateFleetResponse made;
  auto context = MakeContext();
  ASSERT_TRUE(stub_->CreateFleet(context.get(), create, &made).ok());
  EXPECT_EQ(made.settings().max_clusters(), 3u);
  context = MakeContext();
  EXPECT_EQ(stub_->CreateFleet(context.get(), create, &made).error_code(),
            grpc::StatusCode::ALREADY_EXISTS);
  Reply<v1::UploadTracesResponse> accepted =
      UploadTraces(*stub_, kFleet, MakeTraces(spec));
  ASSERT_TRUE(accepted.ok()) << Describe(accepted.status);
  EXPECT_EQ(accepted.response.accepted(), 30u);
  // Its settings survive a restart (they are the fleet's, stored).
  absl::StatusOr<int> stopped = server_->Stop();
  ASSERT_TRUE(stopped.ok() && *stopped == 0);
  ASSERT_TRUE(server_->Start().ok());
  stub_ = MakeStub(server_->address());
  v1::GetFleetRequest get;
  get.set_fleet_id(kFleet);
  v1::GetFleetResponse got;
  context = MakeContext();
  ASSERT_TRUE(stub_->GetFleet(context.get(), get, &got).ok());
  EXPECT_TRUE(got.fleet().own_settings());
  EXPECT_EQ(got.fleet().settings().max_clusters(), 3u);
  EXPECT_EQ(got.fleet().pending_traces() + got.fleet().traces(), 30u);
}

// A fleet's retention is enforced by the server's periodic task, through
// the fleet's log: each robot keeps its newest max_traces_per_robot, the
// watch reports the deletes, and the metric counts them.
TEST_F(LimitsTest, RetentionKeepsEachRobotsNewest) {
  ASSERT_NO_FATAL_FAILURE(Start("retention_interval_seconds: 1\n"));
  TraceSpec spec{.robot_id = "r1", .count = 120, .dimension = 8};
  ASSERT_TRUE(UploadTraces(*stub_, kFleet, MakeTraces(spec)).ok());
  v1::UpdateFleetRequest update;
  update.set_fleet_id(kFleet);
  update.mutable_settings()->set_max_traces_per_robot(25);
  v1::UpdateFleetResponse updated;
  auto context = MakeContext();
  ASSERT_TRUE(stub_->UpdateFleet(context.get(), update, &updated).ok());
  EXPECT_EQ(updated.settings().max_traces_per_robot(), 25u);
  Reply<v1::GetStatsResponse> stats = GetStats(*stub_, kFleet);
  for (const auto give_up =
           std::chrono::steady_clock::now() + std::chrono::seconds(20);
       stats.ok() &&
       stats.response.traces() + stats.response.pending_traces() > 25 &&
       std::chrono::steady_clock::now() < give_up;) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    stats = GetStats(*stub_, kFleet);
  }
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(), 25u);
  Reply<std::vector<v1::MemoryEvent>> events =
      ReadEvents(*stub_, kFleet, 0, stats.response.last_event_id());
  ASSERT_TRUE(events.ok());
  ASSERT_FALSE(events.response.empty());
  EXPECT_EQ(events.response.back().type(), v1::MemoryEvent::TRACES_DELETED);
  // The newest 25 seqs are the ones left.
  v1::GetTracesRequest get;
  get.set_fleet_id(kFleet);
  for (uint64_t seq = 90; seq <= 120; ++seq) {
    v1::TraceKey* key = get.add_keys();
    key->set_robot_id("r1");
    key->set_seq(seq);
  }
  v1::GetTracesResponse got;
  context = MakeContext();
  ASSERT_TRUE(stub_->GetTraces(context.get(), get, &got).ok());
  ASSERT_EQ(got.traces_size(), 25);
  EXPECT_EQ(got.traces(0).seq(), 96u);
}

TEST_F(LimitsTest, StreamsPerClient) {
  ASSERT_NO_FATAL_FAILURE(Start("limits { max_streams_per_client: 2 }\n"));
  TraceSpec spec{.robot_id = "r1", .count = 50, .dimension = 8};
  ASSERT_TRUE(UploadTraces(*stub_, kFleet, MakeTraces(spec)).ok());
  ASSERT_TRUE(Consolidate(*stub_, kFleet).ok());  // events to watch
  // Two open watches hold both slots of this client; each has delivered
  // an event, so both are registered on the server.
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientReader<v1::MemoryEvent>>> watches;
  for (int i = 0; i < 2; ++i) {
    contexts.push_back(MakeContext(std::chrono::seconds(30)));
    v1::WatchMemoryRequest request;
    request.set_fleet_id(kFleet);
    watches.push_back(stub_->WatchMemory(contexts.back().get(), request));
    v1::MemoryEvent event;
    ASSERT_TRUE(watches.back()->Read(&event));
  }
  spec.first_seq = 100;
  ExpectLimit(UploadTraces(*stub_, kFleet, MakeTraces(spec)).status,
              "max_streams_per_client");
  ExpectLimit(ReadEvents(*stub_, kFleet, 0, 1).status,
              "max_streams_per_client");
  for (auto& context : contexts) context->TryCancel();
  for (auto& watch : watches) watch->Finish().IgnoreError();
  watches.clear();
  // Slots are returned when the streams end.
  grpc::Status again;
  for (int attempt = 0; attempt < 50; ++attempt) {
    spec.first_seq = 1000 + attempt * 10;
    again = UploadTraces(*stub_, kFleet, MakeTraces(spec)).status;
    if (again.ok()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_TRUE(again.ok()) << Describe(again);
}

// Issue 32: an upload stream that never sends held its slot for good.
TEST_F(LimitsTest, IdleUploadStreamsAreCancelled) {
  ASSERT_NO_FATAL_FAILURE(
      Start("limits { max_streams_per_client: 1 stream_idle_seconds: 1 }\n"));
  auto context = MakeContext(std::chrono::seconds(30));
  v1::UploadTracesResponse response;
  auto idle = stub_->UploadTraces(context.get(), &response);
  // It holds the client's one slot until the server cancels it.
  TraceSpec spec{.robot_id = "r1", .count = 10, .dimension = 8};
  grpc::Status status;
  const auto start = std::chrono::steady_clock::now();
  do {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    status = UploadTraces(*stub_, kFleet, MakeTraces(spec)).status;
  } while (!status.ok() &&
           std::chrono::steady_clock::now() - start < std::chrono::seconds(10));
  EXPECT_TRUE(status.ok()) << Describe(status);
  EXPECT_EQ(idle->Finish().error_code(), grpc::StatusCode::CANCELLED);
}

// Issue 32: a watch whose client stops reading kept its write in flight and
// its stream slot for good. It is now cancelled after stream_idle_seconds
// without an event taken.
TEST_F(LimitsTest, AWatchWhoseClientStopsReadingIsCancelled) {
  ASSERT_NO_FATAL_FAILURE(
      Start("limits { max_streams_per_client: 2 stream_idle_seconds: 1 }\n"
            "engine { segment_size: 10 }\n"
            "memory { clusters_per_batch: 5 max_clusters: 50 }\n"));
  // A client that never reads, with a small receive window so that the
  // server's writes stall soon.
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_HTTP2_BDP_PROBE, 0);
  args.SetInt(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, 1024);
  auto stalled_stub = v1::MemoryService::NewStub(grpc::CreateCustomChannel(
      server_->address(), grpc::InsecureChannelCredentials(), args));
  auto context = MakeContext(std::chrono::seconds(60));
  v1::WatchMemoryRequest request;
  request.set_fleet_id(kFleet);
  auto stalled = stalled_stub->WatchMemory(context.get(), request);
  // Events (a segment of 10 traces makes 5 clusters) until the server gives
  // up on the watch.
  constexpr char kCancelled[] = "cancelled: the client took no event";
  TraceSpec spec{.robot_id = "r1", .count = 200, .dimension = 8};
  const auto start = std::chrono::steady_clock::now();
  while (!absl::StrContains(server_->Output(), kCancelled) &&
         std::chrono::steady_clock::now() - start < std::chrono::seconds(30)) {
    Reply<v1::UploadTracesResponse> uploaded =
        UploadTraces(*stub_, kFleet, MakeTraces(spec), 10);
    ASSERT_TRUE(uploaded.ok()) << Describe(uploaded.status);
    spec.first_seq += spec.count;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_TRUE(absl::StrContains(server_->Output(), kCancelled))
      << spec.first_seq - 1 << " traces uploaded";
  // Its slot came back: the client's two slots serve two new watches.
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientReader<v1::MemoryEvent>>> watches;
  for (int i = 0; i < 2; ++i) {
    contexts.push_back(MakeContext(std::chrono::seconds(5)));
    watches.push_back(stub_->WatchMemory(contexts.back().get(), request));
    v1::MemoryEvent event;
    EXPECT_TRUE(watches.back()->Read(&event)) << "watch " << i;
  }
  for (size_t i = 0; i < watches.size(); ++i) {
    contexts[i]->TryCancel();
    (void)watches[i]->Finish();
  }
  context->TryCancel();
  (void)stalled->Finish();
}

TEST_F(LimitsTest, CompactedCursorIsOutOfRange) {
  ASSERT_NO_FATAL_FAILURE(
      Start("engine { max_events_per_fleet: 5 segment_size: 20 }\n"
            "memory { clusters_per_batch: 4 max_clusters: 6 }\n"));
  TraceSpec spec{.robot_id = "r1", .count = 100, .dimension = 8};
  // Messages of one segment: each consolidates and adds events.
  ASSERT_TRUE(UploadTraces(*stub_, kFleet, MakeTraces(spec), 20).ok());
  Reply<v1::GetStatsResponse> stats = GetStats(*stub_, kFleet);
  ASSERT_TRUE(stats.ok());
  ASSERT_GT(stats.response.last_event_id(), 5u);
  const uint64_t first = stats.response.first_event_id();
  EXPECT_EQ(stats.response.last_event_id() - first + 1, 5u);
  Reply<std::vector<v1::MemoryEvent>> old = ReadEvents(*stub_, kFleet, 1, 2);
  EXPECT_EQ(old.status.error_code(), grpc::StatusCode::OUT_OF_RANGE)
      << Describe(old.status);
  EXPECT_TRUE(absl::StrContains(old.status.error_message(), "retention"));
  Reply<std::vector<v1::MemoryEvent>> all =
      ReadEvents(*stub_, kFleet, 0, stats.response.last_event_id());
  ASSERT_TRUE(all.ok()) << Describe(all.status);
  ASSERT_EQ(all.response.size(), 5u);
  EXPECT_EQ(all.response.front().id(), first);
}

}  // namespace
}  // namespace fleetmem::testing
