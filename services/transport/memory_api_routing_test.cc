// MemoryApi's routing in distributed mode, against a recording
// FleetMemory: a fleet's calls go to its owner after the caller is
// authorised here, a forwarded call is never forwarded again, Consolidate
// and SampleReplay go through the FleetMemory (the log) at the owner, and
// ListFleets gathers every owner's fleets.
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

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
                       const google::protobuf::Message& request,
                       google::protobuf::Message* response) override {
    forwarded.emplace_back(address, std::string(method));
    if (method == "ListFleets") {
      auto* listed = static_cast<v1::ListFleetsResponse*>(response);
      v1::FleetSummary* fleet = listed->add_fleets();
      fleet->set_fleet_id("theirs");
      fleet->set_replica(address);
      fleet->set_traces(42);
    }
    return absl::OkStatus();
  }
  absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id) override {
    through_log.push_back("Consolidate " + std::string(fleet_id));
    return engine::ConsolidateResult{};
  }
  absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view) override {
    through_log.push_back("SampleReplay " + std::string(fleet_id) + " " +
                          std::string(robot_id) + " " + std::to_string(count));
    return std::vector<core::MemoryTrace>{};
  }

  std::map<std::string, std::string> owners;  // fleet -> owner ("" none)
  std::vector<std::pair<std::string, std::string>> forwarded;
  std::vector<std::string> through_log;

 private:
  const std::string self_ = "me:1";
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
  absl::Status again =
      api_->Call("GetStats", admin, request, &response, /*forwarded=*/true);
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
  v1::ListFleetsResponse mine;
  ASSERT_TRUE(api_->Call("ListFleets", auth::Principal::Anonymous(),
                         v1::ListFleetsRequest(), &mine, /*forwarded=*/true)
                  .ok());
  ASSERT_EQ(mine.fleets_size(), 1);
  EXPECT_EQ(mine.fleets(0).fleet_id(), "mine");
}

}  // namespace
}  // namespace fleetmem::transport
