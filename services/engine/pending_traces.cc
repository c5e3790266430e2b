#include "services/engine/pending_traces.h"

#include <utility>

namespace fleetmem::engine {

void PendingTraces::Add(core::MemoryTrace trace) {
  std::vector<core::MemoryTrace>& robot = by_robot_[trace.robot_id];
  position_[trace.key()] = robot.size();
  ++by_domain_[trace.domain];
  robot.push_back(std::move(trace));
}

std::vector<core::MemoryTrace> PendingTraces::Take(std::string_view robot_id) {
  auto found = by_robot_.find(robot_id);
  if (found == by_robot_.end()) return {};
  std::vector<core::MemoryTrace> taken = std::move(found->second);
  by_robot_.erase(found);
  for (const core::MemoryTrace& trace : taken) {
    position_.erase(trace.key());
    auto domain = by_domain_.find(trace.domain);
    if (domain != by_domain_.end() && --domain->second == 0) {
      by_domain_.erase(domain);
    }
  }
  return taken;
}

void PendingTraces::Clear() {
  by_robot_.clear();
  position_.clear();
  by_domain_.clear();
}

const core::MemoryTrace* PendingTraces::Find(const core::TraceKey& key) const {
  auto position = position_.find(key);
  if (position == position_.end()) return nullptr;
  return &by_robot_.find(key.robot_id)->second[position->second];
}

std::span<const core::MemoryTrace> PendingTraces::Of(
    std::string_view robot_id) const {
  auto found = by_robot_.find(robot_id);
  if (found == by_robot_.end()) return {};
  return found->second;
}

}  // namespace fleetmem::engine
