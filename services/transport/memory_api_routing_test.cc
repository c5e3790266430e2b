// MemoryApi's routing in distributed mode, against a recording
// FleetMemory: a fleet's calls go to its owner after the caller is
// authorised here, a forwarded call is never forwarded again, Consolidate
// and SampleReplay go through the FleetMemory (the log) at the owner, and
// ListFleets gathers every owner's fleets.
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "absl/time/clock.h"
#include "gtest/gtest.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/memory_api.h"

namespace fleetmem::transport {
namespace {

class RecordingDistribution final : public FleetMemory {
 public:
  absl::StatusOr<Uploaded> Upload(std::string_view,
                                  std::span<const core::MemoryTrace>,
                                  const UploadOptions&) override {
    return Uploaded{};
  }
  engine::Backlog Backlog(std::string_view) override { return {}; }
  engine::AliasTable& aliases() override { return *aliases_; }
  absl::StatusOr<std::optional<std::string>> Owner(
      std::string_view fleet_id) override {
    auto it = owners.find(std::string(fleet_id));
    if (it == owners.end() || it->second == self_) return std::nullopt;
    if (it->second.empty()) return absl::UnavailableError("no owner");
    return it->second;
  }
  absl::StatusOr<std::vector<std::pair<std::string, std::string>>> Fleets()
      override {
    return std::vector<std::pair<std::string, std::string>>(owners.begin(),
                                                            owners.end());
  }
  const std::string& self() const override { return self_; }
  absl::Status Forward(const std::string& address, std::string_view method,
                       const google::protobuf::Message&,
                       google::protobuf::Message* response,
                       absl::Time deadline) override {
    forwarded.emplace_back(address, std::string(method));
    deadlines.push_back(deadline);
    if (silent.contains(address)) {
      return absl::DeadlineExceededError("replica " + address + ": silent");
    }
    if (method == "ListFleets") {
      auto* listed = static_cast<v1::ListFleetsResponse*>(response);
      for (const auto& [fleet_id, owner] : owners) {
        if (owner != address) continue;
        v1::FleetSummary* fleet = listed->add_fleets();
        fleet->set_fleet_id(fleet_id);
        fleet->set_replica(address);
        fleet->set_traces(42);
      }
    }
    return absl::OkStatus();
  }
  std::vector<absl::Status> ForwardEach(
      std::span<const std::string> addresses, std::string_view method,
      const google::protobuf::Message& request,
      std::span<google::protobuf::Message* const> responses,
      absl::Time deadline) override {
    std::vector<absl::Status> statuses;
    for (size_t i = 0; i < addresses.size(); ++i) {
      statuses.push_back(
          Forward(addresses[i], method, request, responses[i], deadline));
    }
    return statuses;
  }
  absl::Status CreateFleet(std::string_view fleet_id,
                           const engine::CreateFleetRecord&) override {
    through_log.push_back("CreateFleet " + std::string(fleet_id));
    return absl::OkStatus();
  }
  absl::StatusOr<engine::AppliedRecord> Call(
      std::string_view fleet_id, const engine::LogRecord&) override {
    through_log.push_back("Call " + std::string(fleet_id));
    return engine::AppliedRecord{};
  }
  absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id) override {
    through_log.push_back("Consolidate " + std::string(fleet_id));
    return engine::ConsolidateResult{};
  }
  absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view, const core::ReadFilter*) override {
    through_log.push_back("SampleReplay " + std::string(fleet_id) + " " +
                          std::string(robot_id) + " " + std::to_string(count));
    return std::vector<core::MemoryTrace>{};
  }

  std::map<std::string, std::string> owners;  // fleet -> owner ("" none)
  std::vector<std::pair<std::string, std::string>> forwarded;
  std::vector<absl::Time> deadlines;  // one per forwarded call
  std::set<std::string> silent;       // replicas that never answer
  std::vector<std::string> through_log;

 private:
  const std::string self_ = "me:1";
  std::unique_ptr<engine::StoredAliases> aliases_ =
      *engine::StoredAliases::Open(nullptr);
};

class MemoryApiRoutingTest : public ::testing::Test {
 protected:
  MemoryApiRoutingTest() : store_(storage::NewInMemoryStore()) {
    auto opened = engine::MemoryEngine::Open(
        {}, store_.get(),
        [](size_t dimension) { return index::NewExactIndex(dimension); });
    EXPECT_TRUE(opened.ok()) << opened.status();
    engine_ = *std::move(opened);
    distribution_.owners = {
        {"mine", "me:1"}, {"theirs", "other:2"}, {"orphan", ""}};
    api_ = std::make_unique<MemoryApi>(engine_.get(), &distribution_);
  }

  std::unique_ptr<engine::MemoryStore> store_;
  std::unique_ptr<engine::MemoryEngine> engine_;
  RecordingDistribution distribution_;
  std::unique_ptr<MemoryApi> api_;
};

TEST_F(MemoryApiRoutingTest, AFleetsCallsGoToItsOwnerOnce) {
  const auth::Principal admin = auth::Principal::Anonymous();
  v1::GetStatsRequest request;
  request.set_fleet_id("theirs");
  v1::GetStatsResponse response;
  EXPECT_TRUE(api_->Call("GetStats", admin, request, &response).ok());
  ASSERT_EQ(distribution_.forwarded.size(), 1u);
  EXPECT_EQ(distribution_.forwarded[0],
            (std::pair<std::string, std::string>{"other:2", "GetStats"}));

  // Forwarded here by another replica: served or refused, never sent on.
  CallOptions from_a_replica;
  from_a_replica.forwarded = true;
  absl::Status again =
      api_->Call("GetStats", admin, request, &response, from_a_replica);
  EXPECT_EQ(again.code(), absl::StatusCode::kUnavailable);
  EXPECT_NE(again.message().find("other:2"), std::string::npos) << again;
  EXPECT_EQ(distribution_.forwarded.size(), 1u);

  // A fleet without an owner right now: UNAVAILABLE, nothing forwarded.
  request.set_fleet_id("orphan");
  EXPECT_EQ(api_->Call("GetStats", admin, request, &response).code(),
            absl::StatusCode::kUnavailable);
  // This replica's own fleet is served here (the engine: not created yet).
  request.set_fleet_id("mine");
  EXPECT_EQ(api_->Call("GetStats", admin, request, &response).code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(distribution_.forwarded.size(), 1u);
}

TEST_F(MemoryApiRoutingTest, TheCallerIsAuthorisedBeforeAnythingIsForwarded) {
  auth::Principal robot;
  robot.name = "robot-7";
  robot.role = auth::Role::kRobot;
  robot.robot_id = "robot-7";
  robot.fleets = {"mine"};
  v1::QueryPlaceRequest query;
  query.set_fleet_id("theirs");
  query.add_code(1.0f);
  v1::QueryPlaceResponse matches;
  EXPECT_EQ(api_->Call("QueryPlace", robot, query, &matches).code(),
            absl::StatusCode::kPermissionDenied);
  v1::SampleReplayRequest sample;
  sample.set_fleet_id("mine");
  sample.set_robot_id("robot-8");  // not its own
  sample.set_count(3);
  v1::SampleReplayResponse drawn;
  EXPECT_EQ(api_->Call("SampleReplay", robot, sample, &drawn).code(),
            absl::StatusCode::kPermissionDenied);
  EXPECT_TRUE(distribution_.forwarded.empty());
  EXPECT_TRUE(distribution_.through_log.empty());
}

TEST_F(MemoryApiRoutingTest, WritesAnOwnerDerivesGoThroughTheLog) {
  const auth::Principal admin = auth::Principal::Anonymous();
  v1::SampleReplayRequest sample;
  sample.set_fleet_id("mine");
  sample.set_robot_id("r1");
  sample.set_count(5);
  v1::SampleReplayResponse drawn;
  EXPECT_TRUE(api_->Call("SampleReplay", admin, sample, &drawn).ok());
  v1::ConsolidateRequest consolidate;
  consolidate.set_fleet_id("mine");
  v1::ConsolidateResponse consolidated;
  EXPECT_TRUE(
      api_->Call("Consolidate", admin, consolidate, &consolidated).ok());
  EXPECT_EQ(
      distribution_.through_log,
      (std::vector<std::string>{"SampleReplay mine r1 5", "Consolidate mine"}));
  EXPECT_TRUE(distribution_.forwarded.empty());
}

TEST_F(MemoryApiRoutingTest, ListFleetsGathersEveryOwnersFleets) {
  v1::ListFleetsResponse listed;
  ASSERT_TRUE(api_->Call("ListFleets", auth::Principal::Anonymous(),
                         v1::ListFleetsRequest(), &listed)
                  .ok());
  ASSERT_EQ(listed.fleets_size(), 3);
  std::map<std::string, v1::FleetSummary> by_id;
  for (const v1::FleetSummary& fleet : listed.fleets()) {
    by_id[fleet.fleet_id()] = fleet;
  }
  EXPECT_EQ(by_id["theirs"].replica(), "other:2");
  EXPECT_EQ(by_id["theirs"].traces(), 42u);  // from its owner
  EXPECT_EQ(by_id["orphan"].replica(), "");
  EXPECT_EQ(by_id["mine"].replica(), "me:1");
  ASSERT_EQ(distribution_.forwarded.size(), 1u);  // one ask per owner

  // Asked by another replica: this replica's fleets only.
  CallOptions from_a_replica;
  from_a_replica.forwarded = true;
  v1::ListFleetsResponse mine;
  ASSERT_TRUE(api_->Call("ListFleets", auth::Principal::Anonymous(),
                         v1::ListFleetsRequest(), &mine, from_a_replica)
                  .ok());
  ASSERT_EQ(mine.fleets_size(), 1);
  EXPECT_EQ(mine.fleets(0).fleet_id(), "mine");
}

TEST_F(MemoryApiRoutingTest, AForwardedCallEndsByItsCallersDeadline) {
  v1::GetStatsRequest request;
  request.set_fleet_id("theirs");
  v1::GetStatsResponse response;
  CallOptions how;
  how.deadline = absl::Now() + absl::Seconds(3);
  EXPECT_TRUE(api_->Call("GetStats", auth::Principal::Anonymous(), request,
                         &response, how)
                  .ok());
  ASSERT_EQ(distribution_.deadlines.size(), 1u);
  EXPECT_EQ(distribution_.deadlines[0], how.deadline);
}

// A replica that does not answer (partitioned) costs ListFleets at most
// half its caller's time: its fleets are listed by id and replica, the
// others' with their counts.
TEST_F(MemoryApiRoutingTest, ListFleetsAnswersWithinItsCallersDeadline) {
  distribution_.owners["far"] = "partitioned:3";
  distribution_.silent.insert("partitioned:3");
  CallOptions how;
  const absl::Time now = absl::Now();
  how.deadline = now + absl::Seconds(1);
  v1::ListFleetsResponse listed;
  ASSERT_TRUE(api_->Call("ListFleets", auth::Principal::Anonymous(),
                         v1::ListFleetsRequest(), &listed, how)
                  .ok());
  std::map<std::string, v1::FleetSummary> by_id;
  for (const v1::FleetSummary& fleet : listed.fleets()) {
    by_id[fleet.fleet_id()] = fleet;
  }
  ASSERT_EQ(by_id.size(), 4u);
  EXPECT_EQ(by_id["far"].replica(), "partitioned:3");
  EXPECT_EQ(by_id["far"].traces(), 0u);
  EXPECT_EQ(by_id["theirs"].traces(), 42u);
  // Halfway from when it asked (after `now`, before `after`) to the
  // caller's deadline.
  const absl::Time after = absl::Now();
  ASSERT_EQ(distribution_.deadlines.size(), 2u);  // both owners, one ask
  for (absl::Time asked_until : distribution_.deadlines) {
    EXPECT_GE(asked_until, now + (how.deadline - now) / 2);
    EXPECT_LE(asked_until, after + (how.deadline - after) / 2);
  }

  // Without a deadline (REST): ApiOptions::list_peers_timeout bounds it.
  distribution_.deadlines.clear();
  const absl::Time later = absl::Now();
  ASSERT_TRUE(api_->Call("ListFleets", auth::Principal::Anonymous(),
                         v1::ListFleetsRequest(), &listed)
                  .ok());
  ASSERT_EQ(distribution_.deadlines.size(), 2u);
  EXPECT_LE(distribution_.deadlines[0],
            absl::Now() + ApiOptions().list_peers_timeout);
  EXPECT_GE(distribution_.deadlines[0],
            later + ApiOptions().list_peers_timeout);
}

}  // namespace
}  // namespace fleetmem::transport
