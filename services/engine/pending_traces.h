// A fleet's pending traces: uploaded and applied, awaiting their robot's
// consolidation (Algorithm 1 takes one robot's segment at a time). Part of
// the engine's per-fleet state (memory_engine_fleet.h), kept apart because
// its three views must agree: each robot's traces in arrival order, a
// trace's place among them by key, and the count per domain (statistics
// without walking the traces). Not thread-safe: the fleet's lock guards it.
#ifndef FLEETMEM_SERVICES_ENGINE_PENDING_TRACES_H_
#define FLEETMEM_SERVICES_ENGINE_PENDING_TRACES_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "services/core/types.h"

namespace fleetmem::engine {

class PendingTraces {
 public:
  using ByRobot =
      std::map<std::string, std::vector<core::MemoryTrace>, std::less<>>;

  // Appends `trace` to its robot's (its key must not be pending already).
  void Add(core::MemoryTrace trace);
  // Takes every pending trace of `robot_id` out, in arrival order (none if
  // it has none).
  std::vector<core::MemoryTrace> Take(std::string_view robot_id);
  void Clear();
  // Takes out every pending trace for which `leaves` is true and returns
  // them (each robot's in arrival order); the others keep their order.
  std::vector<core::MemoryTrace> RemoveIf(
      const std::function<bool(const core::MemoryTrace&)>& leaves);
  // Sets the rewards of the pending trace `key` (R = R_ex + R_in) and
  // returns it, or null if it is not pending.
  const core::MemoryTrace* SetReward(const core::TraceKey& key,
                                     float reward_external,
                                     float reward_internal);

  // The pending trace with `key`, or null. A robot's traces only grow
  // until they are taken, so the pointer lives until the next Take,
  // RemoveIf or Clear.
  const core::MemoryTrace* Find(const core::TraceKey& key) const;
  // The robot's pending traces, in arrival order (empty if none).
  std::span<const core::MemoryTrace> Of(std::string_view robot_id) const;

  size_t size() const { return position_.size(); }
  bool empty() const { return position_.empty(); }
  const ByRobot& by_robot() const { return by_robot_; }
  const std::map<std::string, uint64_t, std::less<>>& by_domain() const {
    return by_domain_;
  }

 private:
  ByRobot by_robot_;
  absl::flat_hash_map<core::TraceKey, size_t> position_;
  std::map<std::string, uint64_t, std::less<>> by_domain_;
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_PENDING_TRACES_H_
