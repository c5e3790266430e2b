// The encoder migration of docs/api.md ("Aliases and encoder migration")
// against the real server: a fleet on encoder A behind an alias, a new
// fleet on encoder B filled with what the robots re-encoded, the alias
// switched while 8 robots query through it. No robot may get an error or
// an answer that mixes encoders, and none may go back to the old fleet
// once it met the new one; the alias survives a restart.
#include <atomic>
#include <chrono>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "fleetmem/v1/memory.pb.h"
#include "gtest/gtest.h"
#include "services/common/files.h"
#include "tests/api_helpers.h"
#include "tests/integration_fixture.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

using MigrationTest = ServerTest;

constexpr int kRobots = 4;
constexpr uint64_t kPerRobot = 100;
constexpr int kQueriers = 8;

// Encoder A: 32 dimensions; encoder B: 16, other codes of the same places.
TraceSpec EncoderA(int robot) {
  return {.robot_id = absl::StrCat("robot-", robot),
          .count = kPerRobot,
          .dimension = 32,
          .encoder_version = "enc-A",
          .seed = 1};
}
TraceSpec EncoderB(int robot) {
  TraceSpec spec = EncoderA(robot);
  spec.dimension = 16;
  spec.encoder_version = "enc-B";
  spec.seed = 2;
  return spec;
}

void CreateFleet(v1::MemoryService::Stub& stub, const std::string& fleet,
                 uint32_t dimension, const std::string& encoder) {
  v1::CreateFleetRequest request;
  request.set_fleet_id(fleet);
  request.mutable_settings()->set_code_dimension(dimension);
  request.mutable_settings()->set_encoder_version(encoder);
  v1::CreateFleetResponse response;
  const grpc::Status status =
      stub.CreateFleet(MakeContext().get(), request, &response);
  ASSERT_TRUE(status.ok()) << Describe(status);
}

// Every robot's traces of `spec` into `fleet`, applied.
void Fill(v1::MemoryService::Stub& stub, const std::string& fleet,
          TraceSpec (*spec)(int)) {
  for (int robot = 1; robot <= kRobots; ++robot) {
    const std::vector<v1::MemoryTrace> traces = MakeTraces(spec(robot));
    Reply<v1::UploadTracesResponse> uploaded =
        UploadTraces(stub, fleet, traces);
    ASSERT_TRUE(uploaded.ok()) << Describe(uploaded.status);
    ASSERT_EQ(uploaded.response.accepted(), kPerRobot);
  }
}

// What one querying robot met.
struct Seen {
  int errors = 0;
  int old_answers = 0;
  int new_answers = 0;
  int back_to_old = 0;  // an old answer after a new one
  int mixed = 0;        // an answer whose match is not of its encoder
  int wrong_place = 0;  // the match is not the place asked
  std::string first_error;
};

TEST_F(MigrationTest, RobotsQueryingThroughAnAliasNeverSeeTheSwitch) {
  CreateFleet(stub(), "map-v1", 32, "enc-A");
  Fill(stub(), "map-v1", EncoderA);
  v1::CreateAliasRequest alias;
  alias.set_alias("map");
  alias.set_fleet_id("map-v1");
  v1::CreateAliasResponse made;
  grpc::Status status = stub().CreateAlias(MakeContext().get(), alias, &made);
  ASSERT_TRUE(status.ok()) << Describe(status);
  // The new fleet, filled with what the robots re-encoded (the same
  // robots and seqs, encoder B's codes).
  CreateFleet(stub(), "map-v2", 16, "enc-B");
  Fill(stub(), "map-v2", EncoderB);

  std::atomic<bool> stop = false;
  std::vector<Seen> seen(kQueriers);
  std::vector<std::thread> robots;
  for (int q = 0; q < kQueriers; ++q) {
    robots.emplace_back([&, q] {
      auto stub = MakeStub(server().address());
      Seen& mine = seen[q];
      for (uint64_t i = 0; !stop.load(); ++i) {
        const int robot = 1 + static_cast<int>((q + i) % kRobots);
        const uint64_t seq = 1 + (i * 7 + q) % kPerRobot;
        // A robot mid-migration runs both encoders: it sends both codes.
        v1::QueryPlaceRequest query;
        query.set_fleet_id("map");
        v1::EncoderCode* a = query.add_codes_by_encoder();
        a->set_encoder_version("enc-A");
        *a->mutable_code() = MakeTrace(EncoderA(robot), seq).code();
        v1::EncoderCode* b = query.add_codes_by_encoder();
        b->set_encoder_version("enc-B");
        *b->mutable_code() = MakeTrace(EncoderB(robot), seq).code();
        Reply<v1::QueryPlaceResponse> answer = QueryPlace(*stub, query);
        if (!answer.ok()) {
          if (mine.errors++ == 0) mine.first_error = Describe(answer.status);
          continue;
        }
        const v1::QueryPlaceResponse& got = answer.response;
        const bool is_new = got.fleet_id() == "map-v2";
        if (is_new) {
          ++mine.new_answers;
        } else {
          ++mine.old_answers;
          if (mine.new_answers > 0) ++mine.back_to_old;
        }
        const std::string want = is_new ? "enc-B" : "enc-A";
        if (got.encoder_version() != want || got.matches_size() != 1 ||
            got.matches(0).trace().encoder_version() != want ||
            got.matches(0).trace().code_size() != (is_new ? 16 : 32)) {
          ++mine.mixed;
        } else if (got.matches(0).trace().robot_id() !=
                       absl::StrCat("robot-", robot) ||
                   got.matches(0).trace().seq() != seq) {
          ++mine.wrong_place;
        }
      }
    });
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  v1::SwitchAliasRequest to_new;
  to_new.set_alias("map");
  to_new.set_fleet_id("map-v2");
  v1::SwitchAliasResponse switched;
  status = stub().SwitchAlias(MakeContext().get(), to_new, &switched);
  ASSERT_TRUE(status.ok()) << Describe(status);
  EXPECT_EQ(switched.previous_fleet_id(), "map-v1");
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  stop = true;
  for (std::thread& robot : robots) robot.join();

  int old_answers = 0;
  int new_answers = 0;
  for (int q = 0; q < kQueriers; ++q) {
    SCOPED_TRACE(absl::StrCat("querying robot ", q));
    EXPECT_EQ(seen[q].errors, 0) << seen[q].first_error;
    EXPECT_EQ(seen[q].back_to_old, 0);
    EXPECT_EQ(seen[q].mixed, 0);
    EXPECT_EQ(seen[q].wrong_place, 0);
    old_answers += seen[q].old_answers;
    new_answers += seen[q].new_answers;
  }
  std::cerr << old_answers << " answers from map-v1, " << new_answers
            << " from map-v2, by " << kQueriers << " robots\n";
  EXPECT_GT(old_answers, 0);
  EXPECT_GT(new_answers, 0);

  // The alias is durable: after a restart it names the new fleet.
  StopAndRestart();
  v1::ListAliasesResponse listed;
  status = stub().ListAliases(MakeContext().get(), v1::ListAliasesRequest(),
                              &listed);
  ASSERT_TRUE(status.ok()) << Describe(status);
  ASSERT_EQ(listed.aliases_size(), 1);
  EXPECT_EQ(listed.aliases(0).alias(), "map");
  EXPECT_EQ(listed.aliases(0).fleet_id(), "map-v2");
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), "map");
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.code_dimension(), 16u);
}

// The migration's last step: the old fleet is deleted, its data leaves
// the store's disk at once, the other fleets stay, and after a restart the
// id is free for a new fleet.
TEST_F(MigrationTest, TheOldFleetIsDeletedAndLeavesTheDisk) {
  for (int robot = 1; robot <= 4; ++robot) {
    TraceSpec spec{.robot_id = absl::StrCat("robot-", robot),
                   .count = 6000,
                   .dimension = 128};
    Reply<v1::UploadTracesResponse> uploaded =
        UploadTraces(stub(), "old", MakeTraces(spec));
    ASSERT_TRUE(uploaded.ok()) << Describe(uploaded.status);
  }
  ASSERT_TRUE(UploadTraces(stub(), "kept", MakeTraces({.count = 500})).ok());
  Reply<v1::GetStatsResponse> old = GetStatsApplied(stub(), "old");
  ASSERT_TRUE(old.ok()) << Describe(old.status);
  const uint64_t held = old.response.traces() + old.response.pending_traces();
  Reply<v1::GetStatsResponse> kept = GetStatsApplied(stub(), "kept");
  ASSERT_TRUE(kept.ok());
  const std::string db = data_dir() + "/db";
  // The ingest log keeps its last applied segments for reuse (up to
  // 32 MiB a fleet): left out.
  const uint64_t before = files::BytesUnder(db, db + "/ingest-log");

  v1::DeleteFleetRequest request;
  request.set_fleet_id("old");
  v1::DeleteFleetResponse response;
  grpc::Status status =
      stub().DeleteFleet(MakeContext().get(), request, &response);
  ASSERT_TRUE(status.ok()) << Describe(status);
  EXPECT_EQ(response.traces_deleted(), held);
  const uint64_t after = files::BytesUnder(db, db + "/ingest-log");
  std::cerr << "store and index snapshots: " << before << " bytes with " << held
            << " traces of 128-d, " << after << " after DeleteFleet\n";
  EXPECT_LT(after, before / 4);
  EXPECT_EQ(GetStats(stub(), "old").status.error_code(),
            grpc::StatusCode::NOT_FOUND);

  StopAndRestart();
  EXPECT_EQ(GetStats(stub(), "old").status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  Reply<v1::GetStatsResponse> still = GetStats(stub(), "kept");
  ASSERT_TRUE(still.ok()) << Describe(still.status);
  EXPECT_EQ(still.response.traces() + still.response.pending_traces(),
            kept.response.traces() + kept.response.pending_traces());
  // The id makes a new fleet: the same robot and seqs, another dimension.
  Reply<v1::UploadTracesResponse> again =
      UploadTraces(stub(), "old", MakeTraces({.count = 50, .dimension = 16}));
  ASSERT_TRUE(again.ok()) << Describe(again.status);
  EXPECT_EQ(again.response.accepted(), 50u);
  Reply<v1::GetStatsResponse> anew = GetStatsApplied(stub(), "old");
  ASSERT_TRUE(anew.ok());
  EXPECT_EQ(anew.response.code_dimension(), 16u);
}

}  // namespace
}  // namespace fleetmem::testing
