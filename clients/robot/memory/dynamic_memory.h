// The robot's dynamic memory M_D (BioSLAM Sec. V; memory.md "Refreshing and
// replay"): a small bounded buffer of memory traces that feeds replay.
//
// - Filled by refresh from the fleet's static memory (Eq. 18: the server's
//   SampleReplay draws without replacement with w = gamma^n R, n counted
//   fleet-wide) and by the robot's own new traces.
// - Replay (Eq. 19) draws from it without replacement with the core's
//   sampler and weight w = gamma^n * max(R, floor), where n counts the draws
//   of that trace by this robot (the fleet's count is not used here).
// - When full, the entry of lowest weight is evicted (ties: the one added
//   first).
//
// Refresh replaces every entry that came from the fleet by the new sample
// (keeping the local replay count of a trace that is sampled again) and
// keeps the robot's own traces that the sample does not hold (they may not
// have reached the server yet); then the bound is enforced. Not durable: a
// restarted robot refills it at its first refresh.
//
// Not thread-safe.
#ifndef FLEETMEM_CLIENTS_ROBOT_MEMORY_DYNAMIC_MEMORY_H_
#define FLEETMEM_CLIENTS_ROBOT_MEMORY_DYNAMIC_MEMORY_H_

#include <cstddef>
#include <cstdint>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "services/core/types.h"

namespace fleetmem::robot {

struct DynamicMemoryOptions {
  // |M_D| (the paper's 1,000).
  size_t capacity = 1000;
  // gamma of Eq. 19 (memory.md's 0.9); 1 disables time decay.
  double gamma = 0.9;
  // Rewards below this count as it, so no trace has zero weight (the
  // server's floor).
  double reward_floor = 1e-3;
};

struct ReplayEntry {
  core::MemoryTrace trace;
  // Draws of this trace by this robot's replay (n of Eq. 19).
  uint32_t local_replays = 0;
  // Added from the robot's own observations (not yet seen from the fleet).
  bool local = false;
  // Order of insertion, for ties of eviction.
  uint64_t added = 0;
};

class DynamicMemory {
 public:
  DynamicMemory(std::string robot_id, DynamicMemoryOptions options);

  // Adds one of the robot's own new traces (replacing an entry of the same
  // (robot, seq)), then evicts down to capacity.
  void AddOwn(const core::MemoryTrace& trace);
  // Gives the entry of `trace`'s (robot, seq) its rewards (R_ex, R_in, R),
  // keeping its place and replay count; false if M_D holds no such entry.
  bool SetRewards(const core::MemoryTrace& trace);
  // Eq. 18, see the header comment.
  void Refresh(const std::vector<core::MemoryTrace>& sampled);
  // Eq. 19: min(count, size()) distinct entries drawn with weight
  // gamma^n * max(R, floor); each drawn entry's n is incremented. Draw order.
  std::vector<core::MemoryTrace> Replay(size_t count, std::mt19937_64& rng);

  // Replay weight of an entry.
  double Weight(const ReplayEntry& entry) const;
  size_t size() const { return entries_.size(); }
  const std::vector<ReplayEntry>& entries() const { return entries_; }
  // Entries by the robot that made them (own id included).
  std::map<std::string, size_t> CountByRobot() const;
  const std::string& robot_id() const { return robot_id_; }
  const DynamicMemoryOptions& options() const { return options_; }

 private:
  void EvictToCapacity();

  std::string robot_id_;
  DynamicMemoryOptions options_;
  std::vector<ReplayEntry> entries_;
  uint64_t next_added_ = 0;
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_MEMORY_DYNAMIC_MEMORY_H_
