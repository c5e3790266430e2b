#include "clients/robot/runtime/segment_step.h"

#include <cmath>
#include <set>
#include <string_view>
#include <utility>

#include "absl/strings/str_cat.h"

namespace fleetmem::robot {
namespace {

// R (Eq. 13) of a trace whose R_ex and R_in are set, as `mode` forms it.
float Reward(RewardMode mode, const core::MemoryTrace& t) {
  switch (mode) {
    case RewardMode::kFull:
      return t.reward_external + t.reward_internal;
    case RewardMode::kNoExternal:
      return t.reward_internal;
    case RewardMode::kNoInternal:
      return t.reward_external;
    case RewardMode::kUniform:
      return 1.0f;
  }
  return t.reward_external + t.reward_internal;
}

// The robot's own traces of M_D whose R_ex under the learner changed, as
// the segment's are scored: against the rest of what the robot remembers.
absl::StatusOr<std::vector<core::MemoryTrace>> RescoreRemembered(
    const DynamicMemory& memory, std::span<const core::MemoryTrace> remembered,
    Learner& learner) {
  std::vector<core::MemoryTrace> own, others;
  std::set<uint64_t> own_seqs;
  for (const ReplayEntry& e : memory.entries()) {
    if (e.trace.robot_id != memory.robot_id()) continue;
    own.push_back(e.trace);
    own_seqs.insert(e.trace.seq);
  }
  for (const core::MemoryTrace& t : remembered) {
    if (t.robot_id != memory.robot_id() || !own_seqs.contains(t.seq)) {
      others.push_back(t);
    }
  }
  std::vector<core::MemoryTrace> changed;
  if (own.empty()) return changed;
  absl::StatusOr<std::vector<float>> learned =
      learner.ExternalRewards(own, others);
  if (absl::IsUnimplemented(learned.status())) return changed;
  if (!learned.ok()) return learned.status();
  if (learned->size() != own.size()) {
    return absl::InternalError(absl::StrCat("the learner re-scored ",
                                            learned->size(), " of ", own.size(),
                                            " remembered traces"));
  }
  for (size_t k = 0; k < own.size(); ++k) {
    // Below a float's resolution of R: not worth a write.
    if (std::abs((*learned)[k] - own[k].reward_external) <= 1e-6f) continue;
    core::MemoryTrace& t = changed.emplace_back(std::move(own[k]));
    t.reward_external = (*learned)[k];
    t.reward = Reward(RewardMode::kFull, t);
  }
  return changed;
}

}  // namespace

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
    if (options.rescore_remembered && options.rewards == RewardMode::kFull) {
      absl::StatusOr<std::vector<core::MemoryTrace>> rescored =
          RescoreRemembered(memory, remembered, *learner);
      if (!rescored.ok()) return rescored.status();
      result.rescored = *std::move(rescored);
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
    t.reward = Reward(options.rewards, t);
  }
  result.traces = std::move(segment);
  return result;
}

size_t DomainCount(const DynamicMemory& memory) {
  std::set<std::string_view> domains;
  for (const ReplayEntry& entry : memory.entries()) {
    domains.insert(entry.trace.domain);
  }
  return domains.size();
}

absl::StatusOr<std::string> WarmStart(Learner& learner,
                                      const DynamicMemory& memory) {
  if (const size_t domains = DomainCount(memory); domains < 2) {
    return absl::FailedPreconditionError(absl::StrCat(
        "no warm start: the dynamic memory holds ", memory.size(),
        " traces of ", domains, " domain(s); the head needs two to pair"));
  }
  std::vector<core::MemoryTrace> remembered;
  remembered.reserve(memory.size());
  for (const ReplayEntry& entry : memory.entries()) {
    remembered.push_back(entry.trace);
  }
  return learner.Learn({}, {}, {}, remembered);
}

}  // namespace fleetmem::robot
