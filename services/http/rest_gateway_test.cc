#include "services/http/rest_gateway.h"

#include <memory>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "gmock/gmock.h"
#include "google/protobuf/util/json_util.h"
#include "gtest/gtest.h"
#include "services/auth/authenticator.h"
#include "services/auth/secret.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/embedded_memory.h"

namespace fleetmem::http {
namespace {

using ::testing::HasSubstr;

core::MemoryTrace Trace(const std::string& robot, uint64_t seq) {
  core::MemoryTrace trace;
  trace.robot_id = robot;
  trace.seq = seq;
  trace.domain = seq % 2 == 0 ? "summer" : "winter";
  trace.code = {static_cast<float>(seq % 7), 1.0f, static_cast<float>(seq % 3)};
  trace.place = {static_cast<double>(seq), 2.0 * seq, 0.0, 0.0};
  trace.reward = 1.0f;
  trace.encoder_version = "v1";
  return trace;
}

class RestGatewayTest : public ::testing::Test {
 protected:
  void SetUp() override {
    engine::EngineOptions options;
    options.segment_size = 4;
    options.memory.clusters_per_batch = 2;
    auto engine = engine::MemoryEngine::Open(
        options, store_.get(),
        [](size_t dimension) { return index::NewExactIndex(dimension); });
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = std::move(*engine);
    std::vector<core::MemoryTrace> traces;
    for (uint64_t seq = 1; seq <= 6; ++seq) traces.push_back(Trace("r1", seq));
    ASSERT_TRUE(engine_->Upload("alpha", traces).ok());
    auto memory = transport::EmbeddedMemory::Open(engine_.get(), store_.get());
    ASSERT_TRUE(memory.ok()) << memory.status();
    memory_ = std::move(*memory);
    api_ = std::make_unique<transport::MemoryApi>(engine_.get(), memory_.get());
    auto gateway = RestGateway::Create(
        api_.get(), nullptr,
        [this](std::string_view transport, std::string_view method,
               absl::StatusCode code, double) {
          calls_.push_back(std::string(transport) + " " + std::string(method) +
                           " " + absl::StatusCodeToString(code));
        },
        RestOptions{.max_body_bytes = 1024});
    ASSERT_TRUE(gateway.ok()) << gateway.status();
    gateway_ = std::move(*gateway);
  }

  HttpResponse Get(const std::string& path,
                   std::multimap<std::string, std::string> query = {}) {
    HttpRequest request{.method = "GET", .path = path, .query = query};
    return gateway_->Handle(request);
  }
  HttpResponse Post(const std::string& path, const std::string& body) {
    HttpRequest request{.method = "POST", .path = path, .body = body};
    return gateway_->Handle(request);
  }

  std::unique_ptr<engine::MemoryStore> store_ = storage::NewInMemoryStore();
  std::unique_ptr<engine::MemoryEngine> engine_;
  std::unique_ptr<transport::EmbeddedMemory> memory_;
  std::unique_ptr<transport::MemoryApi> api_;
  std::unique_ptr<RestGateway> gateway_;
  std::vector<std::string> calls_;
};

TEST_F(RestGatewayTest, RoutesComeFromTheProto) {
  std::vector<std::string> routes;
  for (const Route& route : gateway_->routes()) {
    routes.push_back(route.verb + " " + route.pattern);
  }
  EXPECT_THAT(routes, ::testing::IsSupersetOf(
                          {"GET /v1/fleets", "GET /v1/fleets/{fleet_id}/stats",
                           "POST /v1/fleets/{fleet_id}/query",
                           "POST /v1/fleets/{fleet_id}/sample",
                           "POST /v1/fleets/{fleet_id}/consolidate",
                           "GET /v1/fleets/{fleet_id}/clusters",
                           "GET /v1/fleets/{fleet_id}/events",
                           "POST /v1/admin/snapshots"}));
}

TEST_F(RestGatewayTest, StatsEqualTheApiAnswer) {
  HttpResponse response = Get("/v1/fleets/alpha/stats");
  ASSERT_EQ(response.status, 200) << response.body;
  v1::GetStatsResponse from_json;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(response.body, &from_json)
          .ok());
  v1::GetStatsRequest request;
  request.set_fleet_id("alpha");
  v1::GetStatsResponse direct;
  ASSERT_TRUE(
      api_->GetStats(auth::Principal::Anonymous(), request, &direct).ok());
  EXPECT_EQ(from_json.SerializeAsString(), direct.SerializeAsString());
  EXPECT_EQ(from_json.traces() + from_json.pending_traces(), 6u);
  EXPECT_THAT(calls_, ::testing::ElementsAre("http GetStats OK"));
}

TEST_F(RestGatewayTest, QueryWithJsonBody) {
  HttpResponse response =
      Post("/v1/fleets/alpha/query", R"({"code": [1, 1, 1], "k": 2})");
  ASSERT_EQ(response.status, 200) << response.body;
  v1::QueryPlaceResponse answer;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(response.body, &answer).ok());
  EXPECT_EQ(answer.matches_size(), 2);
}

TEST_F(RestGatewayTest, ClustersWithPlacesFromTheQuery) {
  HttpResponse response =
      Get("/v1/fleets/alpha/clusters", {{"includePlaces", "true"}});
  ASSERT_EQ(response.status, 200) << response.body;
  v1::ListClustersResponse answer;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(response.body, &answer).ok());
  ASSERT_GT(answer.clusters_size(), 0);
  size_t places = answer.pending_size();
  for (const v1::ClusterSummary& cluster : answer.clusters()) {
    EXPECT_EQ(cluster.places_size(), static_cast<int>(cluster.trace_count()));
    EXPECT_EQ(cluster.robots().at("r1"), cluster.trace_count());
    places += cluster.places_size();
  }
  EXPECT_EQ(places, 6u);
}

TEST_F(RestGatewayTest, EventsAfterACursor) {
  HttpResponse all = Get("/v1/fleets/alpha/events");
  ASSERT_EQ(all.status, 200) << all.body;
  v1::ListEventsResponse events;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(all.body, &events).ok());
  ASSERT_GT(events.events_size(), 1);
  HttpResponse later = Get("/v1/fleets/alpha/events", {{"after", "1"}});
  v1::ListEventsResponse rest;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(later.body, &rest).ok());
  EXPECT_EQ(rest.events_size(), events.events_size() - 1);
  EXPECT_EQ(rest.events(0).id(), 2u);
}

TEST_F(RestGatewayTest, UnknownFleetIs404WithTheGrpcMessage) {
  HttpResponse response = Get("/v1/fleets/nobody/stats");
  EXPECT_EQ(response.status, 404);
  EXPECT_THAT(response.body, HasSubstr("\"status\":\"NOT_FOUND\""));
  EXPECT_THAT(response.body, HasSubstr("nobody"));
  EXPECT_EQ(Get("/v1/fleets/nobody/events").status, 404);
}

TEST_F(RestGatewayTest, BadJsonIs400) {
  HttpResponse response = Post("/v1/fleets/alpha/query", "{\"code\": [1, 2");
  EXPECT_EQ(response.status, 400);
  EXPECT_THAT(response.body, HasSubstr("request body"));
}

TEST_F(RestGatewayTest, UnknownFieldIs400NamingIt) {
  HttpResponse response =
      Post("/v1/fleets/alpha/query", R"({"code": [1, 1, 1], "kk": 2})");
  EXPECT_EQ(response.status, 400);
  EXPECT_THAT(response.body, HasSubstr("kk"));
}

TEST_F(RestGatewayTest, WrongTypeIs400NamingTheField) {
  HttpResponse response =
      Post("/v1/fleets/alpha/query", R"({"code": [1, 1, 1], "k": "many"})");
  EXPECT_EQ(response.status, 400);
  EXPECT_THAT(response.body, HasSubstr("k"));
  HttpResponse query = Get("/v1/fleets/alpha/events", {{"after", "x"}});
  EXPECT_EQ(query.status, 400);
  EXPECT_THAT(query.body, HasSubstr("after"));
}

TEST_F(RestGatewayTest, UnknownQueryParameterIs400) {
  HttpResponse response = Get("/v1/fleets/alpha/stats", {{"verbose", "1"}});
  EXPECT_EQ(response.status, 400);
  EXPECT_THAT(response.body, HasSubstr("verbose"));
}

TEST_F(RestGatewayTest, BodyFleetMustMatchThePath) {
  HttpResponse response =
      Post("/v1/fleets/alpha/consolidate", R"({"fleetId": "beta"})");
  EXPECT_EQ(response.status, 400);
  EXPECT_THAT(response.body, HasSubstr("fleet_id"));
}

TEST_F(RestGatewayTest, OversizedBodyIs413AndChangesNothing) {
  const std::string body = "{\"code\": [" + std::string(2000, ' ') + "1]}";
  HttpResponse response = Post("/v1/fleets/alpha/query", body);
  EXPECT_EQ(response.status, 413);
  EXPECT_THAT(response.body, HasSubstr("over the limit"));
}

TEST_F(RestGatewayTest, UnknownRouteIs404AndWrongVerbIs405) {
  EXPECT_EQ(Get("/v1/nothing").status, 404);
  EXPECT_EQ(Post("/v1/fleets/alpha/stats", "{}").status, 405);
}

TEST_F(RestGatewayTest, SnapshotsNeedASnapshotRoot) {
  HttpResponse response = Post("/v1/admin/snapshots", R"({"name": "s1"})");
  EXPECT_EQ(response.status, 400);
  EXPECT_THAT(response.body, HasSubstr("FAILED_PRECONDITION"));
  HttpResponse bad = Post("/v1/admin/snapshots", R"({"name": "../x"})");
  EXPECT_EQ(bad.status, 400);
  EXPECT_THAT(bad.body, HasSubstr("name"));
}

TEST(RestGatewayAuthTest, TokensAndRoles) {
  std::unique_ptr<engine::MemoryStore> store = storage::NewInMemoryStore();
  auto engine = engine::MemoryEngine::Open(
      {}, store.get(),
      [](size_t dimension) { return index::NewExactIndex(dimension); });
  ASSERT_TRUE(engine.ok());
  const std::vector<core::MemoryTrace> traces = {Trace("r1", 1)};
  ASSERT_TRUE((*engine)->Upload("alpha", traces).ok());
  absl::StatusOr<std::string> hash = auth::HashSecret("s3cret");
  ASSERT_TRUE(hash.ok());
  std::vector<auth::CredentialEntry> entries;
  entries.push_back(
      {auth::Principal{"viewer", auth::Role::kReader, "", {"alpha"}}, *hash,
       ""});
  auth::Authenticator authenticator(std::move(entries));
  auto memory = transport::EmbeddedMemory::Open(engine->get(), store.get());
  ASSERT_TRUE(memory.ok()) << memory.status();
  transport::MemoryApi api(engine->get(), memory->get());
  auto gateway = RestGateway::Create(&api, &authenticator, nullptr);
  ASSERT_TRUE(gateway.ok());
  HttpRequest request{.method = "GET", .path = "/v1/fleets/alpha/stats"};
  HttpResponse anonymous = (*gateway)->Handle(request);
  EXPECT_EQ(anonymous.status, 401);
  EXPECT_EQ(anonymous.headers.size(), 1u);
  request.authorization = "Bearer viewer:wrong";
  EXPECT_EQ((*gateway)->Handle(request).status, 401);
  HttpRequest consolidate{.method = "POST",
                          .path = "/v1/fleets/alpha/consolidate",
                          .authorization = "Bearer viewer:wrong"};
  EXPECT_EQ((*gateway)->Handle(consolidate).status, 401);
  request.authorization = "Bearer viewer:s3cret";
  EXPECT_EQ((*gateway)->Handle(request).status, 200);
  consolidate.authorization = "Bearer viewer:s3cret";
  HttpResponse denied = (*gateway)->Handle(consolidate);
  EXPECT_EQ(denied.status, 403);
  EXPECT_THAT(denied.body, HasSubstr("only an admin may"));
  HttpRequest other{.method = "GET",
                    .path = "/v1/fleets/beta/stats",
                    .authorization = "Bearer viewer:s3cret"};
  EXPECT_EQ((*gateway)->Handle(other).status, 403);
  HttpRequest fleets{.method = "GET",
                     .path = "/v1/fleets",
                     .authorization = "Bearer viewer:s3cret"};
  EXPECT_THAT((*gateway)->Handle(fleets).body, HasSubstr("alpha"));
}

}  // namespace
}  // namespace fleetmem::http
