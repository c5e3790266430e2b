#include "services/http/http_server.h"

#include <memory>
#include <set>
#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "google/api/annotations.pb.h"
#include "google/protobuf/struct.pb.h"
#include "google/protobuf/util/json_util.h"
#include "gtest/gtest.h"
#include "httplib.h"
#include "services/engine/memory_engine.h"
#include "services/http/dashboard_assets.h"
#include "services/index/exact_index.h"
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
    auto memory = transport::EmbeddedMemory::Open(engine_.get(), store_.get());
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

  std::unique_ptr<engine::MemoryStore> store_ = storage::NewInMemoryStore();
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
  core::MemoryTrace trace;
  trace.robot_id = "r1";
  trace.code = {1, 2, 3};
  trace.reward = 1;
  ASSERT_TRUE(
      engine_->Upload("f1", std::vector<core::MemoryTrace>{trace}).ok());
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

  // Each described route answers (with its answer or the call's own error,
  // never "no route" or "method not allowed"); streams are left after the
  // status line.
  for (const std::string& route : described) {
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

TEST(HttpServerStartTest, BadAddressAndTlsFiles) {
  std::unique_ptr<engine::MemoryStore> store = storage::NewInMemoryStore();
  auto engine = engine::MemoryEngine::Open(
      {}, store.get(),
      [](size_t dimension) { return index::NewExactIndex(dimension); });
  ASSERT_TRUE(engine.ok());
  auto memory = transport::EmbeddedMemory::Open(engine->get(), store.get());
  ASSERT_TRUE(memory.ok()) << memory.status();
  transport::MemoryApi api(engine->get(), memory->get());
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

}  // namespace
}  // namespace fleetmem::http
