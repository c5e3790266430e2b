#include "services/core/robot_numbers.h"

#include "services/core/absl_view.h"

namespace fleetmem::core {

bool RobotNumbers::Add(std::string_view robot_id) {
  if (!numbers_.try_emplace(V(robot_id), static_cast<uint32_t>(ids_.size()))
           .second) {
    return false;
  }
  ids_.emplace_back(robot_id);
  return true;
}

PackedTraceKey RobotNumbers::Pack(std::string_view robot_id, uint64_t seq) {
  auto [it, added] =
      numbers_.try_emplace(V(robot_id), static_cast<uint32_t>(ids_.size()));
  if (added) ids_.emplace_back(robot_id);
  return PackedTraceKey{seq, it->second};
}

std::optional<PackedTraceKey> RobotNumbers::Find(std::string_view robot_id,
                                                 uint64_t seq) const {
  auto it = numbers_.find(V(robot_id));
  if (it == numbers_.end()) return std::nullopt;
  return PackedTraceKey{seq, it->second};
}

void RobotNumbers::Clear() {
  ids_.clear();
  numbers_.clear();
}

}  // namespace fleetmem::core
