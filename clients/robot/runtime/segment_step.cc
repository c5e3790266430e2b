#include "clients/robot/runtime/segment_step.h"

#include <set>
#include <utility>

namespace fleetmem::robot {

absl::StatusOr<SegmentStepResult> RunSegmentStep(
    const SegmentStepOptions& options, std::vector<core::MemoryTrace> segment,
    std::span<const Observation> observations, DynamicMemory& memory,
    std::mt19937_64& rng, Learner* learner, const PlaceRecall& recall) {
  SegmentStepResult result;
  // What the robot remembers: M_D, then the recalled traces of the
  // segment's places (each once).
  std::vector<core::MemoryTrace> remembered;
  remembered.reserve(memory.size());
  for (const ReplayEntry& e : memory.entries()) remembered.push_back(e.trace);
  if (recall && options.recall_per_observation > 0) {
    std::set<std::pair<std::string, uint64_t>> seen;
    for (const core::MemoryTrace& observed : segment) {
      absl::StatusOr<std::vector<core::MemoryTrace>> recalled =
          recall(observed, options.recall_per_observation);
      if (absl::IsNotFound(recalled.status())) break;  // no fleet memory yet
      if (!recalled.ok()) return recalled.status();
      for (core::MemoryTrace& t : *recalled) {
        if (!seen.insert({t.robot_id, t.seq}).second) continue;
        remembered.push_back(std::move(t));
        ++result.recalled;
      }
    }
  }
  const std::vector<core::MemoryTrace> replayed =
      memory.Replay(options.replay_per_segment, rng);
  for (const core::MemoryTrace& t : replayed) {
    (t.robot_id == memory.robot_id() ? result.replayed_own
                                     : result.replayed_peer) += 1;
  }
  std::vector<float> external;
  if (learner != nullptr) {
    absl::StatusOr<std::string> report =
        learner->Learn(segment, observations, replayed, remembered);
    if (!report.ok()) return report.status();
    result.report = *std::move(report);
    absl::StatusOr<std::vector<float>> learned =
        learner->ExternalRewards(segment, remembered);
    if (learned.ok() && learned->size() == segment.size()) {
      external = *std::move(learned);
    } else if (!learned.ok() && !absl::IsUnimplemented(learned.status())) {
      return learned.status();
    }
  }
  if (external.empty()) {
    std::vector<std::vector<float>> codes;
    std::vector<core::Place> places;
    for (const core::MemoryTrace& t : segment) {
      codes.push_back(t.code);
      places.push_back(t.place);
    }
    external = ExternalRewards(codes, places, options.triplet);
  }
  for (size_t k = 0; k < segment.size(); ++k) {
    core::MemoryTrace& t = segment[k];
    t.reward_external = external[k];
    switch (options.rewards) {
      case RewardMode::kFull:
        t.reward = t.reward_external + t.reward_internal;
        break;
      case RewardMode::kNoExternal:
        t.reward = t.reward_internal;
        break;
      case RewardMode::kNoInternal:
        t.reward = t.reward_external;
        break;
      case RewardMode::kUniform:
        t.reward = 1.0f;
        break;
    }
  }
  result.traces = std::move(segment);
  return result;
}

}  // namespace fleetmem::robot
