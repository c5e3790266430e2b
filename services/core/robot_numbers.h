// Robot ids numbered in order of first sight, each id held once, so that a
// map keyed by trace holds (robot number, seq), 16 bytes, instead of a
// TraceKey with its 32-byte string (docs/performance.md, P7). A number is
// never reused or taken back: the table grows with the robots a fleet has
// seen, not with its traces.
#ifndef FLEETMEM_SERVICES_CORE_ROBOT_NUMBERS_H_
#define FLEETMEM_SERVICES_CORE_ROBOT_NUMBERS_H_

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "services/core/types.h"

namespace fleetmem::core {

// A trace key with its robot as a RobotNumbers number.
struct PackedTraceKey {
  uint64_t seq = 0;
  uint32_t robot = 0;

  friend bool operator==(const PackedTraceKey&,
                         const PackedTraceKey&) = default;
  template <typename H>
  friend H AbslHashValue(H h, const PackedTraceKey& key) {
    return H::combine(std::move(h), key.robot, key.seq);
  }
};

class RobotNumbers {
 public:
  // Numbers `robot_id` next; false (nothing changed) if it has a number.
  bool Add(std::string_view robot_id);
  // The key packed, numbering its robot if new.
  PackedTraceKey Pack(std::string_view robot_id, uint64_t seq);
  // The key packed, or nullopt if its robot has no number (no key of it
  // can be in a map of packed keys).
  std::optional<PackedTraceKey> Find(std::string_view robot_id,
                                     uint64_t seq) const;
  // The robot id of `number` (< size()).
  const std::string& robot_id(uint32_t number) const { return ids_[number]; }
  TraceKey Unpack(const PackedTraceKey& key) const {
    return TraceKey{ids_[key.robot], key.seq};
  }
  size_t size() const { return ids_.size(); }
  void Clear();

 private:
  std::vector<std::string> ids_;
  absl::flat_hash_map<std::string, uint32_t> numbers_;
};

// Packs the keys of traces that come in runs of one robot (a cluster's
// traces are mostly one robot's segment) with one lookup of the robot's
// number per run instead of one per key. The robot ids it is given must
// outlive it.
class RunPacker {
 public:
  explicit RunPacker(RobotNumbers& numbers) : numbers_(numbers) {}
  RunPacker(const RunPacker&) = delete;
  RunPacker& operator=(const RunPacker&) = delete;

  // RobotNumbers::Pack.
  PackedTraceKey Pack(const std::string& robot_id, uint64_t seq) {
    if (last_ == nullptr || *last_ != robot_id) {
      number_ = numbers_.Pack(robot_id, 0).robot;
      last_ = &robot_id;
    }
    return PackedTraceKey{seq, number_};
  }

 private:
  RobotNumbers& numbers_;
  const std::string* last_ = nullptr;
  uint32_t number_ = 0;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_ROBOT_NUMBERS_H_
