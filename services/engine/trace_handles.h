// The place index's handles of a fleet's traces, both ways: trace key ->
// handle and handle -> key. Each robot id is held once and a key is packed
// as (robot number, seq) (core::RobotNumbers), so an entry costs two 24-byte
// map slots where two maps of `core::TraceKey` (which holds its robot id, 32
// bytes) took two of 48 (docs/performance.md, P7). Not thread-safe (the fleet's
// lock guards it).
#ifndef FLEETMEM_SERVICES_ENGINE_TRACE_HANDLES_H_
#define FLEETMEM_SERVICES_ENGINE_TRACE_HANDLES_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "services/core/byte_stream.h"
#include "services/core/robot_numbers.h"
#include "services/core/types.h"

namespace fleetmem::engine {

class TraceHandles {
 public:
  // The handle of `key`, or 0 (handles start at 1).
  uint64_t Find(const core::TraceKey& key) const;
  bool contains(const core::TraceKey& key) const { return Find(key) != 0; }
  // The key under `handle`, or nullopt.
  std::optional<core::TraceKey> Key(uint64_t handle) const;
  // Puts key <-> handle, replacing what either had (handle != 0).
  void Assign(const core::TraceKey& key, uint64_t handle);
  // Removes `key` and its handle; returns the handle, or 0 if absent.
  uint64_t Erase(const core::TraceKey& key);
  // Removes `handle` and its key; false if absent.
  bool EraseHandle(uint64_t handle);
  void Reserve(size_t count);
  void Clear();
  size_t size() const { return key_of_.size(); }
  bool empty() const { return key_of_.empty(); }
  // Calls visit(handle, robot id, seq) for every entry, in no set order.
  void ForEach(const std::function<void(uint64_t, std::string_view, uint64_t)>&
                   visit) const;

  // Writes the table for Load: the robot ids once, then (robot number,
  // seq, handle) per entry.
  void Save(core::ByteWriter& out) const;
  // The bytes Save writes.
  uint64_t SavedSize() const;
  // Reads what Save wrote into this empty table. DATA_LOSS (and an empty
  // table) unless every entry is well formed, with distinct keys and
  // distinct handles in [1, next_handle).
  absl::Status Load(core::ByteReader& in, uint64_t next_handle);

 private:
  using Packed = core::PackedTraceKey;
  core::RobotNumbers robots_;
  absl::flat_hash_map<Packed, uint64_t> handle_of_;
  absl::flat_hash_map<uint64_t, Packed> key_of_;
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_TRACE_HANDLES_H_
