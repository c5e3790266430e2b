#include "services/http/http_server.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <poll.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <memory>
#include <mutex>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "google/api/annotations.pb.h"
#include "google/protobuf/struct.pb.h"
#include "google/protobuf/util/json_util.h"
#include "gtest/gtest.h"
#include "httplib.h"
#include "services/auth/authenticator.h"
#include "services/auth/secret.h"
#include "services/engine/memory_engine.h"
#include "services/http/dashboard_assets.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_log.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/embedded_memory.h"

namespace fleetmem::http {
namespace {

using ::testing::HasSubstr;

class HttpServerTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto engine = engine::MemoryEngine::Open(
        {}, store_.get(),
        [](size_t dimension) { return index::NewExactIndex(dimension); });
    ASSERT_TRUE(engine.ok());
    engine_ = std::move(*engine);
    auto memory = transport::EmbeddedMemory::Open(engine_.get(), log_.get());
    ASSERT_TRUE(memory.ok()) << memory.status();
    memory_ = std::move(*memory);
    api_ = std::make_unique<transport::MemoryApi>(engine_.get(), memory_.get());
    auto gateway =
        RestGateway::Create(api_.get(), nullptr, nullptr,
                            {.watch_heartbeat = absl::Milliseconds(100)});
    ASSERT_TRUE(gateway.ok());
    gateway_ = std::move(*gateway);
    HttpServerOptions options;
    options.listen = "127.0.0.1:0";
    options.max_body_bytes = 1000;
    auto server = HttpServer::Start(
        options, {gateway_.get(), [] { return std::string("up 1\n"); },
                  [this] { return ready_; }});
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = std::move(*server);
    client_ = std::make_unique<httplib::Client>("127.0.0.1", server_->port());
  }
  void TearDown() override {
    gateway_->Shutdown();  // as the server does: watches end first
    server_->Stop();
  }
  // One pending trace in `fleet` (3-d, robot r1).
  void UploadOneTrace(const std::string& fleet) {
    core::MemoryTrace trace;
    trace.robot_id = "r1";
    trace.code = {1, 2, 3};
    trace.reward = 1;
    ASSERT_TRUE(
        engine_->Upload(fleet, std::vector<core::MemoryTrace>{trace}).ok());
  }

  std::unique_ptr<engine::MemoryStore> store_ = storage::NewInMemoryStore();
  std::unique_ptr<engine::FleetLog> log_ = storage::NewInMemoryLog();
  std::unique_ptr<engine::MemoryEngine> engine_;
  std::unique_ptr<transport::EmbeddedMemory> memory_;
  std::unique_ptr<transport::MemoryApi> api_;
  std::unique_ptr<RestGateway> gateway_;
  std::unique_ptr<HttpServer> server_;
  std::unique_ptr<httplib::Client> client_;
  bool ready_ = true;
};

TEST_F(HttpServerTest, ProbesMetricsDashboardAndApi) {
  auto health = client_->Get("/healthz");
  ASSERT_TRUE(health);
  EXPECT_EQ(health->status, 200);
  EXPECT_EQ(client_->Get("/readyz")->status, 200);
  ready_ = false;
  EXPECT_EQ(client_->Get("/readyz")->status, 503);
  EXPECT_EQ(client_->Get("/metrics")->body, "up 1\n");
  auto page = client_->Get("/");
  ASSERT_TRUE(page);
  EXPECT_EQ(page->status, 200);
  EXPECT_THAT(page->body, HasSubstr("<title>fleetmem"));
  EXPECT_THAT(page->get_header_value("Content-Type"), HasSubstr("text/html"));
  EXPECT_EQ(client_->Get("/app.js")->status, 200);
  auto fleets = client_->Get("/v1/fleets");
  ASSERT_TRUE(fleets);
  EXPECT_EQ(fleets->status, 200);
  EXPECT_EQ(fleets->body, "{\"fleets\":[]}");
  auto missing = client_->Get("/nothing-here");
  EXPECT_EQ(missing->status, 404);
  EXPECT_THAT(missing->body, HasSubstr("NOT_FOUND"));
}

TEST_F(HttpServerTest, OversizedBodyIsRefused) {
  auto response = client_->Post("/v1/fleets/a/query", std::string(5000, ' '),
                                "application/json");
  ASSERT_TRUE(response);
  EXPECT_EQ(response->status, 413);
  // The setting by its config-file name, the limit and the body's size.
  EXPECT_THAT(response->body, HasSubstr("max_http_body_bytes"));
  EXPECT_THAT(response->body, HasSubstr("limit of 1000 bytes"));
  EXPECT_THAT(response->body, HasSubstr("body of 5000 bytes"));
}

TEST_F(HttpServerTest, EveryDashboardFileIsServed) {
  ASSERT_GE(DashboardFiles().size(), 3u);
  for (const EmbeddedFile& file : DashboardFiles()) {
    auto response = client_->Get(file.path);
    ASSERT_TRUE(response) << file.path;
    EXPECT_EQ(response->status, 200) << file.path;
    EXPECT_EQ(response->body.size(), file.size) << file.path;
  }
}

// The routes memory.proto's google.api.http options name, and the plain
// endpoints: what the server must serve and describe.
std::set<std::string> RoutesToServe() {
  std::set<std::string> routes;
  const google::protobuf::ServiceDescriptor& service =
      *google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(
          "fleetmem.v1.MemoryService");
  for (int i = 0; i < service.method_count(); ++i) {
    const auto& options = service.method(i)->options();
    if (!options.HasExtension(google::api::http)) continue;
    const google::api::HttpRule& rule = options.GetExtension(google::api::http);
    routes.insert(rule.has_get() ? "get " + rule.get() : "post " + rule.post());
  }
  for (const PlainEndpoint& endpoint : PlainEndpoints()) {
    routes.insert(absl::StrCat("get ", endpoint.path));
  }
  return routes;
}

TEST_F(HttpServerTest, OpenApiDescribesExactlyTheRoutesThatAnswer) {
  ASSERT_NO_FATAL_FAILURE(UploadOneTrace("f1"));
  auto answer = client_->Get("/openapi.json");
  ASSERT_TRUE(answer);
  ASSERT_EQ(answer->status, 200);
  google::protobuf::Struct document;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(answer->body, &document)
          .ok());
  const auto& top = document.fields();
  EXPECT_EQ(top.at("openapi").string_value(), "3.0.3");
  std::set<std::string> described;
  for (const auto& [path, item] : top.at("paths").struct_value().fields()) {
    for (const auto& [verb, operation] : item.struct_value().fields()) {
      described.insert(verb + " " + path);
    }
  }
  EXPECT_EQ(described, RoutesToServe());
  // Every request and answer schema is there.
  const auto& schemas = top.at("components")
                            .struct_value()
                            .fields()
                            .at("schemas")
                            .struct_value()
                            .fields();
  EXPECT_TRUE(schemas.contains("fleetmem.v1.UploadTracesRequest"));
  EXPECT_TRUE(schemas.contains("fleetmem.v1.Pose"));
  EXPECT_TRUE(schemas.contains("fleetmem.v1.MemoryEvent"));
  // memory.proto's comments are the schemas' descriptions (issue 48: none
  // before), and a uint32 says its range.
  const auto& event =
      schemas.at("fleetmem.v1.MemoryEvent").struct_value().fields();
  EXPECT_THAT(event.at("properties")
                  .struct_value()
                  .fields()
                  .at("id")
                  .struct_value()
                  .fields()
                  .at("description")
                  .string_value(),
              HasSubstr("Strictly increasing"));
  const auto& count = event.at("properties")
                          .struct_value()
                          .fields()
                          .at("traceCount")
                          .struct_value()
                          .fields();
  EXPECT_EQ(count.at("minimum").number_value(), 0);
  EXPECT_EQ(count.at("maximum").number_value(), 4294967295.0);
  // The bearer requirement (or none, for a server without --auth-file) as
  // written: `[{"bearer": []}, {}]`, and the plain endpoints need nothing
  // (`"security": []`). An empty list once came out as `{}`, which lost
  // the requirement for Swagger UI and generated clients.
  const auto& security = top.at("security").list_value().values();
  ASSERT_EQ(security.size(), 2);
  EXPECT_TRUE(
      security[0].struct_value().fields().at("bearer").has_list_value());
  EXPECT_TRUE(security[1].struct_value().fields().empty());
  const auto& health = top.at("paths")
                           .struct_value()
                           .fields()
                           .at("/healthz")
                           .struct_value()
                           .fields()
                           .at("get")
                           .struct_value()
                           .fields();
  ASSERT_TRUE(health.contains("security"));
  EXPECT_TRUE(health.at("security").has_list_value());
  EXPECT_EQ(health.at("security").list_value().values_size(), 0);

  // Each described route answers (with its answer or the call's own error,
  // never "no route" or "method not allowed"); streams are left after the
  // status line. The fleet's deletion last: after it the fleet's calls
  // answer NOT_FOUND (404) by right.
  std::vector<std::string> routes(described.begin(), described.end());
  std::stable_partition(routes.begin(), routes.end(), [](const auto& route) {
    return route != "post /v1/fleets/{fleet_id}/delete";
  });
  for (const std::string& route : routes) {
    const size_t space = route.find(' ');
    std::string path = route.substr(space + 1);
    if (const size_t variable = path.find("{fleet_id}");
        variable != std::string::npos) {
      path.replace(variable, 10, "f1");
    }
    int status = 0;
    std::string type;
    auto head = [&](const httplib::Response& response) {
      status = response.status;
      type = response.get_header_value("Content-Type");
      return type != "text/event-stream";
    };
    auto body = [](const char*, size_t) { return true; };
    if (route.starts_with("get ")) {
      client_->Get(path, head, body);
    } else {
      auto posted = client_->Post(path, "{}", "application/json");
      ASSERT_TRUE(posted) << route;
      status = posted->status;
    }
    EXPECT_NE(status, 0) << route;
    EXPECT_NE(status, 404) << route;
    EXPECT_NE(status, 405) << route;
    if (route.ends_with("/watch")) EXPECT_EQ(type, "text/event-stream");
  }
}

// An engine on the in-memory store and the API over it.
struct InMemoryApi {
  absl::Status Open() {
    auto opened = engine::MemoryEngine::Open(
        {}, store.get(),
        [](size_t dimension) { return index::NewExactIndex(dimension); });
    if (!opened.ok()) return opened.status();
    engine = std::move(*opened);
    auto embedded = transport::EmbeddedMemory::Open(engine.get(), log.get());
    if (!embedded.ok()) return embedded.status();
    memory = std::move(*embedded);
    api = std::make_unique<transport::MemoryApi>(engine.get(), memory.get());
    return absl::OkStatus();
  }
  std::unique_ptr<engine::MemoryStore> store = storage::NewInMemoryStore();
  std::unique_ptr<engine::FleetLog> log = storage::NewInMemoryLog();
  std::unique_ptr<engine::MemoryEngine> engine;
  std::unique_ptr<transport::EmbeddedMemory> memory;
  std::unique_ptr<transport::MemoryApi> api;
};

TEST(HttpServerStartTest, BadAddressAndTlsFiles) {
  InMemoryApi in_memory;
  ASSERT_TRUE(in_memory.Open().ok());
  transport::MemoryApi& api = *in_memory.api;
  auto gateway = RestGateway::Create(&api, nullptr, nullptr);
  ASSERT_TRUE(gateway.ok());
  HttpServerOptions options;
  options.listen = "nonsense";
  EXPECT_EQ(HttpServer::Start(options, {gateway->get()}).status().code(),
            absl::StatusCode::kInvalidArgument);
  options.listen = "127.0.0.1:0";
  options.tls_cert_file = "/nonexistent/cert.pem";
  options.tls_key_file = "/nonexistent/key.pem";
  absl::Status status = HttpServer::Start(options, {gateway->get()}).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("/nonexistent/cert.pem"));
}

// Issue 32: /metrics answered without credentials with auth on, fleet ids
// and all. Decided: it follows auth (any principal), unless the operator
// sets metrics_without_auth for a scraper on a private network.
TEST(HttpMetricsAuthTest, MetricsFollowAuthUnlessSaidOtherwise) {
  InMemoryApi in_memory;
  ASSERT_TRUE(in_memory.Open().ok());
  transport::MemoryApi& api = *in_memory.api;
  absl::StatusOr<std::string> hash = auth::HashSecret("s3cret");
  ASSERT_TRUE(hash.ok());
  auth::Authenticator authenticator(
      {{auth::Principal{"scraper", auth::Role::kReader, "", {"*"}}, *hash,
        ""}});
  auto gateway = RestGateway::Create(&api, &authenticator, nullptr);
  ASSERT_TRUE(gateway.ok());
  for (const bool without_auth : {false, true}) {
    HttpServerOptions options;
    options.listen = "127.0.0.1:0";
    auto server = HttpServer::Start(
        options, {gateway->get(), [] { return std::string("up 1\n"); },
                  [] { return true; }, without_auth});
    ASSERT_TRUE(server.ok()) << server.status();
    httplib::Client client("127.0.0.1", (*server)->port());
    auto anonymous = client.Get("/metrics");
    ASSERT_TRUE(anonymous);
    EXPECT_EQ(anonymous->status, without_auth ? 200 : 401);
    auto wrong =
        client.Get("/metrics", {{"Authorization", "Bearer scraper:x"}});
    ASSERT_TRUE(wrong);
    EXPECT_EQ(wrong->status, without_auth ? 200 : 401);
    auto scraped =
        client.Get("/metrics", {{"Authorization", "Bearer scraper:s3cret"}});
    ASSERT_TRUE(scraped);
    EXPECT_EQ(scraped->status, 200);
    EXPECT_EQ(scraped->body, "up 1\n");
    EXPECT_EQ(client.Get("/healthz")->status, 200);  // probes stay open
  }
}

// A TCP connection to 127.0.0.1:`port`; -1 if it cannot be made.
int Connect(int port) {
  const int socket = ::socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (connect(socket, reinterpret_cast<sockaddr*>(&address), sizeof(address)) !=
      0) {
    close(socket);
    return -1;
  }
  return socket;
}

// What the server sent on `socket` within `timeout`, until it closed ("" if
// nothing came); `closed` says whether it closed.
std::string ReadUntilClosed(int socket, std::chrono::milliseconds timeout,
                            bool* closed) {
  std::string got;
  *closed = false;
  const auto end = std::chrono::steady_clock::now() + timeout;
  while (std::chrono::steady_clock::now() < end) {
    pollfd wait{socket, POLLIN, 0};
    if (poll(&wait, 1, 50) <= 0) continue;
    char buffer[4096];
    const ssize_t n = recv(socket, buffer, sizeof(buffer), 0);
    if (n <= 0) {
      *closed = true;
      break;
    }
    got.append(buffer, static_cast<size_t>(n));
  }
  return got;
}

// The outside sweep: httplib took the first of two different
// Content-Length headers (how requests are smuggled past a proxy that
// takes the other). Refused with 400, and the connection closed.
TEST_F(HttpServerTest, AmbiguousRequestLengthsAreRefused) {
  for (const std::string& headers :
       {std::string("Content-Length: 2\r\nContent-Length: 30\r\n"),
        std::string("Content-Length: 2\r\nTransfer-Encoding: chunked\r\n")}) {
    SCOPED_TRACE(headers);
    const int socket = Connect(server_->port());
    ASSERT_GE(socket, 0);
    const std::string request = absl::StrCat(
        "POST /v1/fleets/alpha/consolidate HTTP/1.1\r\nHost: 127.0.0.1\r\n",
        headers, "\r\n{}GET /readyz HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
    ASSERT_EQ(send(socket, request.data(), request.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(request.size()));
    bool closed = false;
    const std::string got =
        ReadUntilClosed(socket, std::chrono::milliseconds(2000), &closed);
    close(socket);
    EXPECT_TRUE(absl::StartsWith(got, "HTTP/1.1 400")) << got;
    EXPECT_THAT(got, HasSubstr("ambiguous"));
    EXPECT_TRUE(closed);
    // Nothing after it was read as a request of its own.
    EXPECT_THAT(got, ::testing::Not(HasSubstr("ready")));
  }
  // One length, given twice alike, is fine.
  const int socket = Connect(server_->port());
  const std::string request =
      "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 0\r\n"
      "Content-Length: 0\r\nConnection: close\r\n\r\n";
  ASSERT_EQ(send(socket, request.data(), request.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(request.size()));
  bool closed = false;
  EXPECT_TRUE(absl::StartsWith(
      ReadUntilClosed(socket, std::chrono::milliseconds(2000), &closed),
      "HTTP/1.1 200"));
  close(socket);
}

// `curl -X POST http://.../v1/fleets/f1/consolidate` (operations.md) sends
// neither Content-Length nor a Content-Type: an empty body, served like
// `{}`, the connection kept for the next request.
TEST_F(HttpServerTest, APostWithoutABodyIsServed) {
  ASSERT_NO_FATAL_FAILURE(UploadOneTrace("f1"));
  const int socket = Connect(server_->port());
  ASSERT_GE(socket, 0);
  const std::string request =
      "POST /v1/fleets/f1/consolidate HTTP/1.1\r\nHost: 127.0.0.1\r\n"
      "User-Agent: curl/7.88.1\r\nAccept: */*\r\n\r\n";
  ASSERT_EQ(send(socket, request.data(), request.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(request.size()));
  bool closed = false;
  const std::string got =
      ReadUntilClosed(socket, std::chrono::milliseconds(1000), &closed);
  EXPECT_TRUE(absl::StartsWith(got, "HTTP/1.1 200")) << got;
  EXPECT_THAT(got, HasSubstr("\"consolidatedTraces\""));
  EXPECT_FALSE(closed);
  // The connection serves the next request.
  const std::string next =
      "GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n";
  ASSERT_EQ(send(socket, next.data(), next.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(next.size()));
  EXPECT_THAT(ReadUntilClosed(socket, std::chrono::milliseconds(3000), &closed),
              HasSubstr("ok\n"));
  close(socket);
  EXPECT_EQ(engine_->GetStats("f1")->pending_traces, 0u);
}

class HttpConnectionLimitsTest : public HttpServerTest {
 protected:
  void Restart(ConnectionLimits limits) {
    server_->Stop();
    HttpServerOptions options;
    options.listen = "127.0.0.1:0";
    options.connections = std::move(limits);
    auto server = HttpServer::Start(
        options, {gateway_.get(), [] { return std::string("up 1\n"); },
                  [] { return true; }});
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = std::move(*server);
    client_ = std::make_unique<httplib::Client>("127.0.0.1", server_->port());
    client_->set_read_timeout(3, 0);
  }
};

// Issue 32: eight connections sending a header line every 3 s held all eight
// threads; /readyz went unanswered. Now 50 such connections leave the
// probes and the API answering, and each is closed at its head deadline.
TEST_F(HttpConnectionLimitsTest, SlowClientsDoNotStarveTheProbes) {
  ConnectionLimits limits;
  limits.head_timeout = absl::Seconds(1);
  ASSERT_NO_FATAL_FAILURE(Restart(limits));
  std::vector<int> slow;
  for (int i = 0; i < 50; ++i) {
    const int socket = Connect(server_->port());
    ASSERT_GE(socket, 0);
    const std::string line = "GET /readyz HTTP/1.1\r\n";
    ASSERT_EQ(send(socket, line.data(), line.size(), MSG_NOSIGNAL),
              static_cast<ssize_t>(line.size()));
    slow.push_back(socket);
  }
  std::atomic<bool> stop = false;
  std::thread trickle([&] {  // one header line every 300 ms on each
    while (!stop.load()) {
      for (int socket : slow) {
        (void)send(socket, "X-Slow: 1\r\n", 11, MSG_NOSIGNAL | MSG_DONTWAIT);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(300));
    }
  });
  for (int i = 0; i < 5; ++i) {
    auto ready = client_->Get("/readyz");
    ASSERT_TRUE(ready) << "probe " << i << ": "
                       << httplib::to_string(ready.error());
    EXPECT_EQ(ready->status, 200);
    auto fleets = client_->Get("/v1/fleets");
    ASSERT_TRUE(fleets);
    EXPECT_EQ(fleets->status, 200);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  // Past the head deadline every slow connection is closed, unanswered.
  for (int socket : slow) {
    bool closed = false;
    const std::string got =
        ReadUntilClosed(socket, std::chrono::milliseconds(3000), &closed);
    EXPECT_TRUE(closed);
    EXPECT_EQ(got, "");
  }
  stop = true;
  trickle.join();
  for (int socket : slow) close(socket);
}

// The outside sweep: past the 256-connection limit (300 slow connections
// from 5 addresses), /readyz answered 503 to 33 of 60 probes. Over a limit
// a connection's request line is still read and a probe answered: with
// every slot held by slow connections (a header line every 300 ms), 20
// probes on new connections are all answered 200 within 1 s, while an API
// call over the limit gets 503.
TEST_F(HttpConnectionLimitsTest, ProbesAreAnsweredPastTheConnectionLimit) {
  ConnectionLimits limits;
  limits.max_connections = 16;
  limits.max_connections_per_client = 16;
  limits.head_timeout = absl::Seconds(30);
  ASSERT_NO_FATAL_FAILURE(Restart(limits));
  std::vector<int> slow;
  for (int i = 0; i < 40; ++i) {  // 16 held, 24 more waiting to be refused
    const int socket = Connect(server_->port());
    ASSERT_GE(socket, 0);
    const std::string line = "GET /v1/fleets HTTP/1.1\r\n";
    (void)send(socket, line.data(), line.size(), MSG_NOSIGNAL);
    slow.push_back(socket);
  }
  std::atomic<bool> stop = false;
  std::thread trickle([&] {
    while (!stop.load()) {
      for (int socket : slow) {
        (void)send(socket, "X-Slow: 1\r\n", 11, MSG_NOSIGNAL | MSG_DONTWAIT);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(300));
    }
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(200));
  auto ask = [&](const std::string& path) {
    const int socket = Connect(server_->port());
    const std::string request =
        absl::StrCat("GET ", path, " HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n");
    (void)send(socket, request.data(), request.size(), MSG_NOSIGNAL);
    bool closed = false;
    std::string got =
        ReadUntilClosed(socket, std::chrono::milliseconds(1000), &closed);
    close(socket);
    return got;
  };
  int answered = 0;
  for (int i = 0; i < 20; ++i) {
    const auto sent = std::chrono::steady_clock::now();
    const std::string got = ask("/readyz");
    const bool fast = std::chrono::steady_clock::now() - sent <
                      std::chrono::milliseconds(1000);
    if (absl::StartsWith(got, "HTTP/1.1 200") &&
        absl::StrContains(got, "ready") && fast) {
      ++answered;
    }
  }
  EXPECT_EQ(answered, 20);
  EXPECT_THAT(ask("/healthz"), HasSubstr("200"));
  EXPECT_THAT(ask("/v1/fleets"), HasSubstr("503"));
  stop = true;
  trickle.join();
  for (int socket : slow) close(socket);
}

TEST_F(HttpConnectionLimitsTest, AClientsConnectionsAreCapped) {
  ConnectionLimits limits;
  limits.max_connections_per_client = 4;
  std::atomic<int> refused = 0;
  limits.on_refused = [&refused](const std::string&) { ++refused; };
  ASSERT_NO_FATAL_FAILURE(Restart(limits));
  std::vector<int> idle;
  for (int i = 0; i < 4; ++i) idle.push_back(Connect(server_->port()));
  const int over = Connect(server_->port());
  ASSERT_GE(over, 0);
  bool closed = false;
  const std::string got =
      ReadUntilClosed(over, std::chrono::milliseconds(2000), &closed);
  EXPECT_TRUE(closed);
  EXPECT_THAT(got, HasSubstr("503"));
  EXPECT_THAT(got, HasSubstr("max_connections_per_client"));
  EXPECT_EQ(refused.load(), 1);
  close(over);
  for (int socket : idle) close(socket);
  // Their slots come back when they close.
  bool answered = false;
  for (int attempt = 0; attempt < 50 && !answered; ++attempt) {
    auto ready = client_->Get("/readyz");
    answered = ready && ready->status == 200;
    if (!answered) std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_TRUE(answered);
}

// httplib bounds a header line (8 KiB), not their number: a client sending
// header lines as fast as it can, within the head deadline, grew the
// server's memory without bound. The head is now capped at max_head_bytes;
// an ordinary request with a few kilobytes of headers is still served.
TEST_F(HttpConnectionLimitsTest, AnEndlessRequestHeadIsCut) {
  ConnectionLimits limits;
  limits.max_head_bytes = 64 * 1024;
  std::mutex mu;
  std::vector<std::string> reasons;
  limits.on_refused = [&](const std::string& reason) {
    std::lock_guard<std::mutex> lock(mu);
    reasons.push_back(reason);
  };
  ASSERT_NO_FATAL_FAILURE(Restart(limits));
  httplib::Headers headers;
  for (int i = 0; i < 8; ++i) {
    headers.emplace(absl::StrCat("X-Big-", i), std::string(1000, 'a'));
  }
  auto ready = client_->Get("/readyz", headers);
  ASSERT_TRUE(ready) << httplib::to_string(ready.error());
  EXPECT_EQ(ready->status, 200);

  const int socket = Connect(server_->port());
  ASSERT_GE(socket, 0);
  const std::string start = "GET /readyz HTTP/1.1\r\nHost: 127.0.0.1\r\n";
  ASSERT_EQ(send(socket, start.data(), start.size(), MSG_NOSIGNAL),
            static_cast<ssize_t>(start.size()));
  const std::string line =
      absl::StrCat("X-More: ", std::string(4000, 'b'), "\r\n");
  // Header lines as fast as the server takes them, until it cuts the
  // connection (64 MiB or 10 s at most).
  auto cut = [&] {
    std::lock_guard<std::mutex> lock(mu);
    return !reasons.empty();
  };
  size_t sent = 0;
  const auto give_up =
      std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!cut() && sent < (size_t{64} << 20) &&
         std::chrono::steady_clock::now() < give_up) {
    pollfd wait{socket, POLLOUT, 0};
    if (poll(&wait, 1, 50) <= 0) continue;
    const ssize_t n =
        send(socket, line.data(), line.size(), MSG_NOSIGNAL | MSG_DONTWAIT);
    if (n < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) continue;
    if (n <= 0) break;  // reset by the server
    sent += static_cast<size_t>(n);
  }
  // The server shut the connection down (its side ends unanswered).
  bool closed = false;
  const std::string got =
      ReadUntilClosed(socket, std::chrono::milliseconds(3000), &closed);
  EXPECT_TRUE(closed);
  EXPECT_EQ(got, "");
  close(socket);
  std::lock_guard<std::mutex> lock(mu);
  ASSERT_EQ(reasons.size(), 1u) << "sent " << sent << " bytes, not cut";
  EXPECT_THAT(reasons[0], HasSubstr("a request head over 65536 bytes"));
  std::cout << reasons[0] << "; " << sent << " bytes sent\n";
}

// The outside sweep: 4 watch slots for all clients; after 4 watchers had
// closed, new ones got 429 for 13.7 s (a closed connection was noticed at
// the next keep-alive, every 15 s), and over 200 connect/close cycles 188
// got 429. A closed connection now gives back its slot within
// watch_liveness: 200 cycles, each opening a watch, reading its first
// bytes and closing, with the keep-alive at its 15 s default, are all
// served.
TEST_F(HttpServerTest, AClosedWatchGivesBackItsSlotAtOnce) {
  std::vector<core::MemoryTrace> traces;
  core::MemoryTrace trace;
  trace.robot_id = "r";
  trace.seq = 1;
  trace.code = {1, 0, 0};
  traces.push_back(trace);
  ASSERT_TRUE(engine_->Upload("alpha", traces).ok());
  auto gateway =
      RestGateway::Create(api_.get(), nullptr, nullptr, {.max_watches = 4});
  ASSERT_TRUE(gateway.ok());
  HttpServerOptions options;
  options.listen = "127.0.0.1:0";
  auto server = HttpServer::Start(options, {gateway->get(), nullptr, nullptr});
  ASSERT_TRUE(server.ok()) << server.status();
  const std::string request =
      "GET /v1/fleets/alpha/watch HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n";
  int refused = 0;
  int served = 0;
  for (int cycle = 0; cycle < 200; ++cycle) {
    const int socket = Connect((*server)->port());
    ASSERT_GE(socket, 0);
    ASSERT_EQ(send(socket, request.data(), request.size(), 0),
              static_cast<ssize_t>(request.size()));
    std::string got;
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (got.find("\r\n\r\n") == std::string::npos &&
           std::chrono::steady_clock::now() < end) {
      pollfd wait{socket, POLLIN, 0};
      if (poll(&wait, 1, 50) <= 0) continue;
      char buffer[4096];
      const ssize_t n = recv(socket, buffer, sizeof(buffer), 0);
      if (n <= 0) break;
      got.append(buffer, static_cast<size_t>(n));
    }
    close(socket);
    if (absl::StartsWith(got, "HTTP/1.1 200")) ++served;
    if (absl::StartsWith(got, "HTTP/1.1 429")) ++refused;
    // A watcher that comes back at once, as an EventSource does.
    std::this_thread::sleep_for(
        std::chrono::milliseconds(cycle % 4 == 3 ? 100 : 0));
  }
  EXPECT_EQ(refused, 0);
  EXPECT_EQ(served, 200);
  (*gateway)->Shutdown();
  (*server)->Stop();
}

}  // namespace
}  // namespace fleetmem::http
