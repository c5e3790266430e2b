// libFuzzer harness: one REST request (verb, path, query, JSON body) through
// the gateway's routing, JSON parsing, query parsing and the API, on an
// engine with one small fleet on the in-memory store (made once; the
// gateway and the engine are meant to take any request without harm).
//
// Input layout: "VERB PATH?QUERY\n" then the body (bytes after the first
// newline). Query "a=1&b=2" without decoding.
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_split.h"
#include "services/engine/memory_engine.h"
#include "services/http/rest_gateway.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_log.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/embedded_memory.h"

namespace {

namespace fm = fleetmem;

struct World {
  World() {
    fm::engine::EngineOptions options;
    options.segment_size = 4;
    options.memory.clusters_per_batch = 2;
    options.memory.max_clusters = 3;
    options.now_ns = [] { return int64_t{1}; };
    engine = std::move(*fm::engine::MemoryEngine::Open(
        options, store.get(),
        [](size_t dimension) { return fm::index::NewExactIndex(dimension); }));
    std::vector<fm::core::MemoryTrace> traces;
    for (uint64_t seq = 1; seq <= 6; ++seq) {
      fm::core::MemoryTrace trace;
      trace.robot_id = "r1";
      trace.seq = seq;
      trace.code = {static_cast<float>(seq), 1.0f};
      trace.reward = 1.0f;
      traces.push_back(trace);
    }
    engine->Upload("f", traces).IgnoreError();
    memory = std::move(
        *fm::transport::EmbeddedMemory::Open(engine.get(), log.get()));
    api =
        std::make_unique<fm::transport::MemoryApi>(engine.get(), memory.get());
    gateway = std::move(*fm::http::RestGateway::Create(
        api.get(), nullptr, nullptr, {.max_body_bytes = 1 << 16}));
  }
  std::unique_ptr<fm::engine::MemoryStore> store =
      fm::storage::NewInMemoryStore();
  std::unique_ptr<fm::engine::FleetLog> log = fm::storage::NewInMemoryLog();
  std::unique_ptr<fm::engine::MemoryEngine> engine;
  std::unique_ptr<fm::transport::EmbeddedMemory> memory;
  std::unique_ptr<fm::transport::MemoryApi> api;
  std::unique_ptr<fm::http::RestGateway> gateway;
};

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  static World* world = new World();
  const std::string input(reinterpret_cast<const char*>(data), size);
  const size_t newline = input.find('\n');
  const std::string line = input.substr(0, newline);
  fm::http::HttpRequest request;
  const size_t space = line.find(' ');
  if (space == std::string::npos) return 0;
  request.method = line.substr(0, space);
  std::string target = line.substr(space + 1);
  const size_t question = target.find('?');
  request.path = target.substr(0, question);
  if (question != std::string::npos) {
    for (absl::string_view pair :
         absl::StrSplit(target.substr(question + 1), '&', absl::SkipEmpty())) {
      std::vector<std::string> parts =
          absl::StrSplit(pair, absl::MaxSplits('=', 1));
      request.query.emplace(parts[0], parts.size() > 1 ? parts[1] : "");
    }
  }
  if (newline != std::string::npos) request.body = input.substr(newline + 1);
  // Snapshots would write to disk; the world has no snapshot root, so they
  // fail with FAILED_PRECONDITION before touching anything.
  world->gateway->Handle(request);
  return 0;
}
