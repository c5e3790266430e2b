// libFuzzer harness: the bytes of one UploadTraces message, as the server
// receives them, through parsing (ParseUploadMessage), conversion and the
// engine's validation and upload path (a fresh engine on the in-memory store
// per input, with a small segment so that consolidation runs too).
#include <cstddef>
#include <cstdint>
#include <memory>
#include <vector>

#include "absl/strings/string_view.h"
#include "services/core/validation.h"
#include "services/engine/memory_engine.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_reactor.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace fm = fleetmem;
  absl::StatusOr<fm::v1::UploadTracesRequest> request =
      fm::transport::ParseUploadMessage(
          absl::string_view(reinterpret_cast<const char*>(data), size));
  if (!request.ok() || request->traces().empty()) return 0;
  const std::vector<fm::core::MemoryTrace> traces =
      fm::transport::UploadedTracesFromProto(request->traces());
  const std::string fleet =
      fm::core::ValidateId("fleet_id", request->fleet_id()).ok()
          ? request->fleet_id()
          : "fuzz";
  fm::engine::EngineOptions options;
  options.segment_size = 4;
  options.memory.clusters_per_batch = 2;
  options.memory.max_clusters = 3;
  options.memory.max_traces_per_cluster = 2;
  options.now_ns = [] { return int64_t{1}; };
  std::unique_ptr<fm::engine::MemoryStore> store =
      fm::storage::NewInMemoryStore();
  auto engine = fm::engine::MemoryEngine::Open(
      options, store.get(),
      [](size_t dimension) { return fm::index::NewExactIndex(dimension); });
  if (!engine.ok()) return 0;
  if (!(*engine)->Upload(fleet, traces).ok()) return 0;
  (*engine)->Consolidate(fleet).IgnoreError();
  (*engine)->SampleReplay(fleet, traces.front().robot_id, 3).IgnoreError();
  (*engine)->GetStats(fleet).IgnoreError();
  return 0;
}
