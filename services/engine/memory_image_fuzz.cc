// libFuzzer harness: bytes as a memory image (the part of an index snapshot
// that a restart after a clean stop takes the clusters from), through
// LoadMemoryImage's checks; an image that decodes saves again to one that
// decodes to the same clusters.
#include <cstddef>
#include <cstdint>
#include <map>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "services/core/byte_stream.h"
#include "services/engine/memory_image.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace engine = fleetmem::engine;
  namespace core = fleetmem::core;
  core::ByteReader in(
      std::span<const char>(reinterpret_cast<const char*>(data), size));
  absl::StatusOr<std::vector<core::Cluster>> clusters =
      engine::LoadMemoryImage(in);
  if (!clusters.ok()) return 0;
  std::map<uint64_t, core::Cluster> by_id;
  for (core::Cluster& cluster : *clusters) {
    by_id.emplace(cluster.id, std::move(cluster));  // the first of an id
  }
  std::string bytes;
  core::ByteWriter out([&bytes](std::span<const char> chunk) {
    bytes.append(chunk.data(), chunk.size());
  });
  engine::SaveMemoryImage(
      by_id,
      [&by_id](uint64_t id) {
        return std::span<const float>(by_id.at(id).centroid);
      },
      out);
  uint64_t length = 0;
  core::ByteReader again(bytes);
  if (!again.Get(&length) || length != again.remaining()) __builtin_trap();
  absl::StatusOr<std::vector<core::Cluster>> back =
      engine::LoadMemoryImage(again);
  if (!back.ok() || back->size() != by_id.size() || again.remaining() != 0) {
    __builtin_trap();
  }
  auto want = by_id.begin();
  for (const core::Cluster& cluster : *back) {
    if (cluster.id != want->first ||
        cluster.traces.size() != want->second.traces.size() ||
        cluster.centroid.size() != want->second.centroid.size()) {
      __builtin_trap();
    }
    ++want;
  }
  return 0;
}
