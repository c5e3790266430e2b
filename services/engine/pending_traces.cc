#include "services/engine/pending_traces.h"

#include <algorithm>
#include <iterator>
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

std::vector<core::MemoryTrace> PendingTraces::RemoveIf(
    const std::function<bool(const core::MemoryTrace&)>& leaves) {
  std::vector<core::MemoryTrace> removed;
  for (auto robot = by_robot_.begin(); robot != by_robot_.end();) {
    std::vector<core::MemoryTrace>& traces = robot->second;
    const auto first_leaving = std::stable_partition(
        traces.begin(), traces.end(),
        [&](const core::MemoryTrace& trace) { return !leaves(trace); });
    for (auto it = first_leaving; it != traces.end(); ++it) {
      position_.erase(it->key());
      auto domain = by_domain_.find(it->domain);
      if (domain != by_domain_.end() && --domain->second == 0) {
        by_domain_.erase(domain);
      }
      removed.push_back(std::move(*it));
    }
    if (first_leaving == traces.end()) {
      ++robot;
      continue;
    }
    traces.erase(first_leaving, traces.end());
    for (size_t i = 0; i < traces.size(); ++i) position_[traces[i].key()] = i;
    robot = traces.empty() ? by_robot_.erase(robot) : std::next(robot);
  }
  return removed;
}

const core::MemoryTrace* PendingTraces::SetReward(const core::TraceKey& key,
                                                  float reward_external,
                                                  float reward_internal) {
  auto position = position_.find(key);
  if (position == position_.end()) return nullptr;
  core::MemoryTrace& trace =
      by_robot_.find(key.robot_id)->second[position->second];
  trace.reward_external = reward_external;
  trace.reward_internal = reward_internal;
  trace.reward = reward_external + reward_internal;
  return &trace;
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
