// What a robot does at the end of each segment before it seals it (BioSLAM
// Algorithm 3, lines 3-6; memory.md "Refreshing and replay"):
//
//   replay: draw from the dynamic memory M_D                   (Eq. 19)
//   recall: the fleet's traces of each new observation's place
//           (QueryPlace with a position prior), the partners of Eq. 7
//   learn:  the learner trains on the segment, the replayed traces and
//           the rest of M_D with the recalled traces
//   reward: R_ex of each new trace under the learner (Eq. 11), or the
//           triplet loss in code space when it has none; R (Eq. 13)
//
// fleetmem-robot's agent (agent.h) and fleetmem-eval's lifelong evaluation
// (tools/eval/lifelong.cc) both run this step, so the published figures
// measure the code a robot runs. What comes after it differs by caller and
// is theirs: the robot seals the traces into its durable upload queue, the
// evaluation uploads and consolidates at once (or keeps a reservoir); both
// then add the traces to M_D and refresh it (Eq. 18).
//
// Pure: no I/O of its own (recall is a callback), no threads.
#ifndef FLEETMEM_CLIENTS_ROBOT_RUNTIME_SEGMENT_STEP_H_
#define FLEETMEM_CLIENTS_ROBOT_RUNTIME_SEGMENT_STEP_H_

#include <cstdint>
#include <functional>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "clients/robot/memory/dynamic_memory.h"
#include "clients/robot/sensing/learner.h"
#include "clients/robot/sensing/observation.h"
#include "clients/robot/sensing/rewards.h"
#include "services/core/types.h"

namespace fleetmem::robot {

// How R is formed from R_ex and R_in (Eq. 13). A robot uses kFull; the
// others are the evaluation's ablations.
enum class RewardMode {
  kFull,        // R = R_ex + R_in
  kNoExternal,  // R = R_in
  kNoInternal,  // R = R_ex
  kUniform,     // R = 1
};

struct SegmentStepOptions {
  // Traces drawn from M_D per segment for replay (Eq. 19).
  size_t replay_per_segment = 64;
  // Traces recalled per new observation (0: no recall).
  size_t recall_per_observation = 4;
  RewardMode rewards = RewardMode::kFull;
  // R_ex in code space, for a learner without its own (or none).
  TripletOptions triplet;
  // Re-score the robot's own remembered traces (its entries of M_D) under
  // the learner once it learned the segment: the learner's R_ex of them now
  // (Eq. 11), for the fleet to take by UpdateRewards (Reverb's
  // mutate_priorities), so that the next refresh (Eq. 18) draws with the
  // head the robot has now rather than the one it had when it uploaded
  // them. Only with a learner that has its own R_ex (the code-space triplet
  // of rewards.h does not change as the robot learns) and rewards kFull.
  bool rescore_remembered = false;
};

// The fleet's traces of an observation's place: the k nearest to its code
// within a radius of its place (QueryPlace with a position prior). NOT_FOUND
// means the fleet has no memory yet: recall stops for the segment. Any other
// error is the step's.
using PlaceRecall =
    std::function<absl::StatusOr<std::vector<core::MemoryTrace>>(
        const core::MemoryTrace& observed, size_t k)>;

struct SegmentStepResult {
  // The segment's traces, in order, with reward_external and reward set.
  std::vector<core::MemoryTrace> traces;
  // Replayed traces of the robot's own and of its peers.
  uint64_t replayed_own = 0;
  uint64_t replayed_peer = 0;
  // Distinct traces recalled for the segment's places.
  uint64_t recalled = 0;
  // The learner's report (empty without a learner).
  std::string report;
  // rescore_remembered: the robot's own traces of M_D whose R_ex changed,
  // with the new reward_external and reward (reward_internal as it was).
  std::vector<core::MemoryTrace> rescored;
};

// One segment's step. `segment` holds the new traces (robot_id, domain,
// code, place, reward_internal set); `observations` their raw observations
// or nothing; `memory` is M_D (read, not changed); `rng` draws the replay;
// `learner` and `recall` may be null/empty. Errors of the learner or of
// recall are returned as they are, with nothing learned after them.
absl::StatusOr<SegmentStepResult> RunSegmentStep(
    const SegmentStepOptions& options, std::vector<core::MemoryTrace> segment,
    std::span<const Observation> observations, DynamicMemory& memory,
    std::mt19937_64& rng, Learner* learner, const PlaceRecall& recall);

// The warm start of a robot joining a fleet (issue 47): before its first
// observation its learner learns from what its first refresh brought into
// M_D (its peers' traces, of every domain the fleet holds: Learn with no
// segment and M_D as the remembered traces), so that it recognises its
// peers' places across domains from its first frame instead of after its
// first segment. Only when M_D holds at least two domains: fitted on one
// domain alone (a fleet that has driven only in summer) the metric head
// learned what tells summer places apart and lost what carries across
// seasons (make demo's learned rows fell from WR 0.849 to 0.777 on the
// robots' own winter frames, 0.591 to 0.567 on their peers'). Returns the
// learner's report; FAILED_PRECONDITION when M_D holds fewer than two
// domains.
absl::StatusOr<std::string> WarmStart(Learner& learner,
                                      const DynamicMemory& memory);
// The domains of M_D's traces: WarmStart needs two.
size_t DomainCount(const DynamicMemory& memory);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_RUNTIME_SEGMENT_STEP_H_
