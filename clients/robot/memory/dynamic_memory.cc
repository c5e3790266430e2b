#include "clients/robot/memory/dynamic_memory.h"

#include <algorithm>
#include <utility>

#include "absl/container/flat_hash_map.h"
#include "services/core/importance_sampler.h"

namespace fleetmem::robot {

DynamicMemory::DynamicMemory(std::string robot_id, DynamicMemoryOptions options)
    : robot_id_(std::move(robot_id)), options_(options) {}

double DynamicMemory::Weight(const ReplayEntry& entry) const {
  return core::ReplayWeight(entry.trace.reward, entry.local_replays,
                            options_.gamma, options_.reward_floor);
}

void DynamicMemory::AddOwn(const core::MemoryTrace& trace) {
  auto same = std::find_if(entries_.begin(), entries_.end(),
                           [&](const ReplayEntry& entry) {
                             return entry.trace.key() == trace.key();
                           });
  if (same != entries_.end()) entries_.erase(same);
  entries_.push_back(ReplayEntry{.trace = trace,
                                 .local_replays = 0,
                                 .local = true,
                                 .added = next_added_++});
  EvictToCapacity();
}

bool DynamicMemory::SetRewards(const core::MemoryTrace& trace) {
  for (ReplayEntry& entry : entries_) {
    if (entry.trace.key() != trace.key()) continue;
    entry.trace.reward_external = trace.reward_external;
    entry.trace.reward_internal = trace.reward_internal;
    entry.trace.reward = trace.reward;
    return true;
  }
  return false;
}

void DynamicMemory::Refresh(const std::vector<core::MemoryTrace>& sampled) {
  absl::flat_hash_map<core::TraceKey, uint32_t> replays;
  for (const ReplayEntry& entry : entries_) {
    replays[entry.trace.key()] = entry.local_replays;
  }
  std::vector<ReplayEntry> next;
  absl::flat_hash_map<core::TraceKey, bool> in_sample;
  for (const core::MemoryTrace& trace : sampled) {
    if (!in_sample.emplace(trace.key(), true).second) continue;
    auto it = replays.find(trace.key());
    next.push_back(
        ReplayEntry{.trace = trace,
                    .local_replays = it == replays.end() ? 0 : it->second,
                    .local = false,
                    .added = next_added_++});
  }
  for (ReplayEntry& entry : entries_) {
    if (entry.local && !in_sample.contains(entry.trace.key())) {
      next.push_back(std::move(entry));
    }
  }
  entries_ = std::move(next);
  EvictToCapacity();
}

std::vector<core::MemoryTrace> DynamicMemory::Replay(size_t count,
                                                     std::mt19937_64& rng) {
  std::vector<double> weights;
  weights.reserve(entries_.size());
  for (const ReplayEntry& entry : entries_) weights.push_back(Weight(entry));
  std::vector<core::MemoryTrace> drawn;
  for (size_t i : core::SampleWithoutReplacement(weights, count, rng)) {
    ++entries_[i].local_replays;
    drawn.push_back(entries_[i].trace);
  }
  return drawn;
}

std::map<std::string, size_t> DynamicMemory::CountByRobot() const {
  std::map<std::string, size_t> counts;
  for (const ReplayEntry& entry : entries_) ++counts[entry.trace.robot_id];
  return counts;
}

void DynamicMemory::EvictToCapacity() {
  if (entries_.size() <= options_.capacity) return;
  // Keep the `capacity` entries of highest weight; ties keep the newer.
  std::vector<size_t> order(entries_.size());
  for (size_t i = 0; i < order.size(); ++i) order[i] = i;
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) {
    const double wa = Weight(entries_[a]), wb = Weight(entries_[b]);
    if (wa != wb) return wa > wb;
    return entries_[a].added > entries_[b].added;
  });
  order.resize(options_.capacity);
  std::sort(order.begin(), order.end());
  std::vector<ReplayEntry> kept;
  kept.reserve(order.size());
  for (size_t i : order) kept.push_back(std::move(entries_[i]));
  entries_ = std::move(kept);
}

}  // namespace fleetmem::robot
