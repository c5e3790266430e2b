#include "services/http/rest_gateway.h"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "google/protobuf/util/json_util.h"
#include "gtest/gtest.h"
#include "services/auth/authenticator.h"
#include "services/auth/secret.h"
#include "services/common/sanitizers.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_log.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/embedded_memory.h"

namespace fleetmem::http {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

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

// `response` with a streamed JSON answer written into its body (as the
// HTTP server sends it); watches (event streams) are left as they are.
HttpResponse Whole(HttpResponse response) {
  if (response.stream && response.content_type == "application/json") {
    response.stream([&](std::string_view piece) {
      response.body.append(piece);
      return true;
    });
    response.stream = nullptr;
  }
  return response;
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
    auto memory = transport::EmbeddedMemory::Open(engine_.get(), log_.get());
    ASSERT_TRUE(memory.ok()) << memory.status();
    memory_ = std::move(*memory);
    transport::ApiOptions api_options;
    api_options.on_upload_bytes = [this](std::string_view fleet, size_t bytes) {
      uploaded_bytes_[std::string(fleet)] += bytes;
    };
    api_ = std::make_unique<transport::MemoryApi>(engine_.get(), memory_.get(),
                                                  api_options);
    auto gateway = RestGateway::Create(
        api_.get(), nullptr,
        [this](std::string_view transport, std::string_view method,
               absl::StatusCode code, double) {
          calls_.push_back(std::string(transport) + " " + std::string(method) +
                           " " + absl::StatusCodeToString(code));
        },
        RestOptions{.max_body_bytes = 1024,
                    .max_watches = 1,
                    .max_watch = absl::Milliseconds(300),
                    .watch_heartbeat = absl::Milliseconds(50)});
    ASSERT_TRUE(gateway.ok()) << gateway.status();
    gateway_ = std::move(*gateway);
  }

  HttpResponse Get(const std::string& path,
                   std::multimap<std::string, std::string> query = {}) {
    HttpRequest request{.method = "GET", .path = path, .query = query};
    return Whole(gateway_->Handle(request));
  }
  HttpResponse Post(const std::string& path, const std::string& body) {
    HttpRequest request{.method = "POST", .path = path, .body = body};
    return Whole(gateway_->Handle(request));
  }

  std::unique_ptr<engine::MemoryStore> store_ = storage::NewInMemoryStore();
  std::unique_ptr<engine::FleetLog> log_ = storage::NewInMemoryLog();
  std::unique_ptr<engine::MemoryEngine> engine_;
  std::unique_ptr<transport::EmbeddedMemory> memory_;
  std::unique_ptr<transport::MemoryApi> api_;
  std::unique_ptr<RestGateway> gateway_;
  std::vector<std::string> calls_;
  std::map<std::string, size_t> uploaded_bytes_;
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

// Issue 44 (the outside sweep): protobuf's JSON parser took nested code
// arrays (flattened), duplicate keys (the last one kept) and enum numbers
// the API does not define. Each is now 400 naming the field, and nothing
// is stored.
TEST_F(RestGatewayTest, LenientJsonIsRefused) {
  struct Case {
    std::string path, body, expected;
  };
  const std::vector<Case> cases = {
      {"/v1/fleets/alpha/query", R"({"code": [[1, 1], [1]], "k": 2})",
       "code[0] is an array"},
      {"/v1/fleets/alpha/query", R"({"code": [1, 1, 1], "k": 2, "k": 3})",
       "k\\\" appears twice in the request"},
      {"/v1/fleets/alpha/traces",
       R"({"traces": [{"robotId": "r9", "seq": 1, "robotId": "r8",
                       "code": [1, 1, 1]}]})",
       "robotId\\\" appears twice in traces[0]"},
      {"/v1/fleets/alpha/traces",
       R"({"traces": [{"robotId": "r9", "seq": 1, "code": [1, 1, 1]}],
           "ack": 7})",
       "7 is not a value of UploadAck"},
      {"/v1/fleets/alpha/traces",
       R"({"traces": [{"robotId": "r9", "seq": 1, "code": [1, 1, 1]}],
           "ack": "UPLOAD_ACK_SOMETIMES"})",
       "UPLOAD_ACK_SOMETIMES is not a value of UploadAck"},
  };
  const uint64_t before = engine_->GetStats("alpha")->pending_traces;
  for (const Case& c : cases) {
    SCOPED_TRACE(c.body);
    HttpResponse response = Post(c.path, c.body);
    EXPECT_EQ(response.status, 400) << response.body;
    EXPECT_THAT(response.body, HasSubstr(c.expected));
  }
  EXPECT_EQ(engine_->GetStats("alpha")->pending_traces, before);
  // Well-formed ones still pass.
  EXPECT_EQ(
      Post("/v1/fleets/alpha/query", R"({"code": [1, 1, 1], "k": 2})").status,
      200);
}

// Issue 44: answers that may hold traces keep their room in a budget of
// bytes in flight until their client has taken them; past it a call waits
// answer_wait, then gets 503 having read nothing. Answers without traces
// (stats) are not held back.
TEST_F(RestGatewayTest, AnswersNotYetTakenAreBoundedInBytes) {
  auto gateway =
      RestGateway::Create(api_.get(), nullptr, nullptr,
                          RestOptions{.max_answer_bytes_in_flight = 1 << 20,
                                      .max_answer_bytes = 1 << 20,
                                      .answer_wait = absl::Milliseconds(100)});
  ASSERT_TRUE(gateway.ok()) << gateway.status();
  const HttpRequest list{.method = "GET", .path = "/v1/fleets/alpha/traces"};
  HttpResponse taken_slowly = (*gateway)->Handle(list);
  ASSERT_EQ(taken_slowly.status, 200);
  ASSERT_TRUE(taken_slowly.stream);
  // The first answer's bytes are held until its stream goes: a second
  // reservation of max_answer_bytes does not fit beside them.
  HttpResponse refused = (*gateway)->Handle(list);
  EXPECT_EQ(refused.status, 503) << refused.body;
  EXPECT_THAT(refused.body, HasSubstr("max_answer_bytes_in_flight"));
  EXPECT_EQ(Whole((*gateway)->Handle(
                      {.method = "GET", .path = "/v1/fleets/alpha/stats"}))
                .status,
            200);
  EXPECT_THAT(Whole(std::move(taken_slowly)).body, HasSubstr("traces"));
  HttpResponse again = Whole((*gateway)->Handle(list));
  EXPECT_EQ(again.status, 200) << again.body;
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
  EXPECT_THAT(response.body, HasSubstr("over the server's limit"));
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
  std::unique_ptr<engine::FleetLog> log = storage::NewInMemoryLog();
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
  auto memory = transport::EmbeddedMemory::Open(engine->get(), log.get());
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
  EXPECT_THAT(Whole((*gateway)->Handle(fleets)).body, HasSubstr("alpha"));
}

// What a watch's stream writes until it ends (or until `pieces` pieces,
// when the writer says the client is gone).
std::string Streamed(const HttpResponse& response, size_t pieces = SIZE_MAX) {
  std::string text;
  size_t written = 0;
  response.stream([&](std::string_view piece) {
    if (piece.empty()) return written < pieces;  // is the client there?
    text += piece;
    return ++written < pieces;
  });
  return text;
}

TEST_F(RestGatewayTest, UploadOverRestIsOneMessageOfAStream) {
  const std::string body = R"({"traces": [
      {"robotId": "r2", "seq": "1", "code": [1, 0, 0], "reward": 1,
       "encoderVersion": "v1"},
      {"robotId": "r2", "seq": "2", "code": [0, 1, 0], "reward": 1,
       "encoderVersion": "v1",
       "pose": {"x": 5}}],
      "ack": "UPLOAD_ACK_APPLIED"})";
  HttpResponse stored = Post("/v1/fleets/alpha/traces", body);
  ASSERT_EQ(stored.status, 200) << stored.body;
  EXPECT_THAT(stored.body, HasSubstr("\"accepted\":\"2\""));
  EXPECT_THAT(stored.body, HasSubstr("\"applied\":true"));
  HttpResponse again = Post("/v1/fleets/alpha/traces", body);
  EXPECT_THAT(again.body, HasSubstr("\"duplicates\":\"2\""));
  // The engine's checks, with nothing stored.
  HttpResponse wrong = Post("/v1/fleets/alpha/traces",
                            R"({"traces": [{"robotId": "r2", "seq": "3",
                                "code": [1, 0], "reward": 1,
                                "encoderVersion": "v1"}]})");
  EXPECT_EQ(wrong.status, 400);
  EXPECT_THAT(wrong.body, HasSubstr("dimension"));
  const std::vector<engine::RobotStats> robots =
      engine_->GetStats("alpha")->robots;
  ASSERT_EQ(robots.back().robot_id, "r2");
  EXPECT_EQ(robots.back().received, 2u);
  EXPECT_THAT(calls_, testing::Contains("http UploadTraces OK"));
  // Both stored messages are counted (as gRPC's are), the refused one not.
  v1::UploadTracesRequest parsed;
  ASSERT_TRUE(google::protobuf::util::JsonStringToMessage(body, &parsed).ok());
  parsed.set_fleet_id("alpha");
  EXPECT_EQ(uploaded_bytes_["alpha"], 2 * parsed.ByteSizeLong());
}

TEST_F(RestGatewayTest, WatchIsServerSentEventsResumedByLastEventId) {
  ASSERT_EQ(Post("/v1/fleets/alpha/consolidate", "").status, 200);
  const uint64_t last = engine_->GetStats("alpha")->last_event_id;
  ASSERT_GE(last, 2u);
  HttpResponse watch = Get("/v1/fleets/alpha/watch");
  ASSERT_EQ(watch.status, 200) << watch.body;
  EXPECT_EQ(watch.content_type, "text/event-stream");
  ASSERT_TRUE(watch.stream);
  // Every event, then heartbeats until max_watch ends the stream.
  const std::string all = Streamed(watch);
  EXPECT_THAT(all, HasSubstr("retry: 1000\n\nid: 1\nevent: CLUSTER_ADDED\n"
                             "data: {\"id\":\"1\""));
  EXPECT_THAT(all, HasSubstr(absl::StrCat("id: ", last, "\n")));
  EXPECT_THAT(all, HasSubstr(": keep-alive\n\n"));
  watch = {};  // gives its slot back

  // An EventSource that reconnects sends the last id it saw.
  HttpRequest resume{
      .method = "GET", .path = "/v1/fleets/alpha/watch", .last_event_id = "1"};
  const std::string rest = Streamed(gateway_->Handle(resume));
  EXPECT_THAT(rest, Not(HasSubstr("id: 1\n")));
  EXPECT_THAT(rest, HasSubstr("id: 2\n"));
  // A writer that fails (the client went away) ends the stream at once.
  const std::string one = Streamed(Get("/v1/fleets/alpha/watch"), 2);
  EXPECT_THAT(one, HasSubstr("id: 1\n"));
  EXPECT_THAT(one, Not(HasSubstr("id: 2\n")));
}

TEST_F(RestGatewayTest, WatchChecksComeBeforeTheStreamAndSlotsAreBounded) {
  EXPECT_EQ(Get("/v1/fleets/no such/watch").status, 400);
  HttpRequest bad_id{
      .method = "GET", .path = "/v1/fleets/alpha/watch", .last_event_id = "x"};
  EXPECT_EQ(gateway_->Handle(bad_id).status, 400);
  HttpResponse first = Get("/v1/fleets/alpha/watch");
  ASSERT_EQ(first.status, 200);
  HttpResponse second = Get("/v1/fleets/alpha/watch");
  EXPECT_EQ(second.status, 429);
  EXPECT_THAT(second.body, HasSubstr("max_watches"));
  first = {};
  EXPECT_EQ(Get("/v1/fleets/alpha/watch").status, 200);
  gateway_->Shutdown();
  EXPECT_EQ(Get("/v1/fleets/alpha/watch").status, 503);
}

// Issue 32: on an open loopback port (the demo's), a page of any site could
// POST (text/plain, Origin http://evil.example) and run consolidate or take a
// snapshot, and any Host was answered, so DNS rebinding could read it all.
TEST_F(RestGatewayTest, CrossSiteRequestsAreRefused) {
  auto gateway = RestGateway::Create(
      api_.get(), nullptr, nullptr,
      RestOptions{.loopback_hosts_only = true,
                  .allowed_origins = {"https://ops.example"}});
  ASSERT_TRUE(gateway.ok()) << gateway.status();
  auto call = [&](const std::string& method, const std::string& path,
                  const std::string& host, const std::string& origin,
                  const std::string& type) {
    return (*gateway)
        ->Handle({.method = method,
                  .path = path,
                  .body = method == "POST" ? "{}" : "",
                  .host = host,
                  .origin = origin,
                  .content_type = type})
        .status;
  };
  const std::string consolidate = "/v1/fleets/alpha/consolidate";
  const uint64_t before = engine_->GetStats("alpha")->consolidations;
  EXPECT_EQ(call("POST", consolidate, "127.0.0.1:8080", "http://evil.example",
                 "text/plain"),
            403);
  EXPECT_EQ(call("POST", consolidate, "127.0.0.1:8080", "http://evil.example",
                 "application/json"),
            403);
  EXPECT_EQ(call("POST", consolidate, "127.0.0.1:8080", "", "text/plain"), 415);
  EXPECT_EQ(engine_->GetStats("alpha")->consolidations, before);
  // DNS rebinding: the page's own name, resolved to 127.0.0.1.
  EXPECT_EQ(call("GET", "/v1/fleets/alpha/stats", "evil.example:8080", "", ""),
            403);
  EXPECT_EQ(call("POST", consolidate, "evil.example:8080",
                 "http://evil.example:8080", "application/json"),
            403);
  // The server's own pages, curl, and an allowed origin.
  EXPECT_EQ(call("GET", "/v1/fleets/alpha/stats", "localhost:8080", "", ""),
            200);
  EXPECT_EQ(call("GET", "/v1/fleets/alpha/stats", "[::1]:8080", "", ""), 200);
  EXPECT_EQ(call("GET", "/v1/fleets/alpha/stats", "", "", ""), 200);  // 1.0
  EXPECT_EQ(call("POST", consolidate, "127.0.0.1:8080", "http://127.0.0.1:8080",
                 "application/json"),
            200);
  EXPECT_EQ(call("POST", consolidate, "127.0.0.1:8080", "", ""), 200);
  EXPECT_EQ(call("POST", consolidate, "127.0.0.1:8080", "https://ops.example",
                 "application/json; charset=utf-8"),
            200);
}

// The process's resident bytes now.
size_t ResidentBytes() {
  std::ifstream statm("/proc/self/statm");
  size_t pages = 0, resident = 0;
  statm >> pages >> resident;
  return resident * static_cast<size_t>(sysconf(_SC_PAGESIZE));
}

TEST(AnswerJsonTest, IsProtobufsJsonOfTheWholeAnswer) {
  v1::ListClustersResponse answer;
  for (int i = 0; i < 3; ++i) {
    v1::ClusterSummary* cluster = answer.add_clusters();
    cluster->set_cluster_id(10 + i);
    (*cluster->mutable_robots())["r1"] = i;
    cluster->add_places()->set_seq(i);
  }
  answer.add_pending()->set_robot_id("r\"traces\":[]");
  google::protobuf::util::JsonPrintOptions print;
  print.always_print_primitive_fields = true;
  std::string want;
  ASSERT_TRUE(
      google::protobuf::util::MessageToJsonString(answer, &want, print).ok());
  absl::StatusOr<std::string> got = AnswerJson(&answer);
  ASSERT_TRUE(got.ok()) << got.status();
  EXPECT_EQ(*got, want);
  v1::ListTracesResponse empty;
  want.clear();
  ASSERT_TRUE(
      google::protobuf::util::MessageToJsonString(empty, &want, print).ok());
  EXPECT_EQ(*AnswerJson(&empty), want);
}

// Issue 32: a page of 10,000 traces of 4,096 dimensions once built 257 MB of
// JSON through a tree of several GB. Now a page ends at max_read_bytes and
// is printed a trace at a time; issue 44: and written as printed, never
// held whole (8 such pages at once took +793 MiB): the call's peak stays
// under 96 MiB.
TEST(RestGatewayMemoryTest, TheLargestPageOfALargeFleetStaysBounded) {
  constexpr size_t kDimension = 4096;
  constexpr size_t kTraces = 1200;
  std::unique_ptr<engine::MemoryStore> store = storage::NewInMemoryStore();
  std::unique_ptr<engine::FleetLog> log = storage::NewInMemoryLog();
  auto engine = engine::MemoryEngine::Open(
      engine::EngineOptions{}, store.get(),
      [](size_t dimension) { return index::NewExactIndex(dimension); });
  ASSERT_TRUE(engine.ok()) << engine.status();
  std::mt19937 rng(7);
  std::normal_distribution<float> normal;
  for (size_t first = 0; first < kTraces; first += 400) {
    std::vector<core::MemoryTrace> traces;
    for (size_t i = first; i < first + 400; ++i) {
      core::MemoryTrace trace = Trace("r1", i + 1);
      trace.code.resize(kDimension);
      for (float& value : trace.code) value = normal(rng);
      traces.push_back(std::move(trace));
    }
    ASSERT_TRUE((*engine)->Upload("big", traces).ok());
  }
  auto memory = transport::EmbeddedMemory::Open(engine->get(), log.get());
  ASSERT_TRUE(memory.ok()) << memory.status();
  transport::MemoryApi api(engine->get(), memory->get());
  auto gateway = RestGateway::Create(&api, nullptr, nullptr, RestOptions{});
  ASSERT_TRUE(gateway.ok()) << gateway.status();

  size_t listed = 0;
  std::string token;
  size_t largest_rise = 0;
  do {
    std::multimap<std::string, std::string> query = {{"pageSize", "10000"}};
    if (!token.empty()) query.emplace("pageToken", token);
    const size_t before = ResidentBytes();
    std::atomic<bool> done = false;
    size_t peak = before;
    std::thread sampler([&] {
      while (!done.load()) {
        peak = std::max(peak, ResidentBytes());
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
      }
    });
    // The answer goes out as printed, to a client that takes every piece
    // (its bytes counted, not kept: what the server holds is measured).
    HttpResponse streamed = (*gateway)->Handle(
        {.method = "GET", .path = "/v1/fleets/big/traces", .query = query});
    size_t sent = 0;
    ASSERT_TRUE(streamed.stream);
    streamed.stream([&sent](std::string_view piece) {
      sent += piece.size();
      return true;
    });
    streamed = HttpResponse();
    done = true;
    sampler.join();
    largest_rise = std::max(largest_rise, peak - before);
    // The same page whole, to read it.
    HttpResponse response = Whole((*gateway)->Handle(
        {.method = "GET", .path = "/v1/fleets/big/traces", .query = query}));
    ASSERT_EQ(response.status, 200) << response.body.substr(0, 300);
    EXPECT_EQ(response.body.size(), sent);
    v1::ListTracesResponse page;
    ASSERT_TRUE(
        google::protobuf::util::JsonStringToMessage(response.body, &page).ok());
    ASSERT_GE(page.traces_size(), 1);
    EXPECT_LE(page.ByteSizeLong(),
              engine::EngineOptions{}.max_read_bytes + page.traces_size() * 64);
    listed += page.traces_size();
    token = page.next_page_token();
  } while (!token.empty());
  EXPECT_EQ(listed, kTraces);
  RecordProperty("largest_rss_rise_mib", std::to_string(largest_rise >> 20));
  // Not under AddressSanitizer, whose quarantine holds freed memory. The
  // page itself is at most max_read_bytes (32 MiB); its JSON (about three
  // times that) is never held whole.
  if (!common::kSanitizerAllocator) EXPECT_LT(largest_rise, size_t{96} << 20);
}

}  // namespace
}  // namespace fleetmem::http
