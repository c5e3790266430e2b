// What a robot learns per segment (BioSLAM Algorithm 3's inner loop): the
// interface the segment step (clients/robot/runtime/segment_step.h) calls
// and the learners of clients/robot/learning/ implement. Here, below both,
// so that the learning module does not include the runtime's headers: a
// learner improves how places are encoded and told apart.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_LEARNER_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_LEARNER_H_

#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "clients/robot/sensing/observation.h"
#include "services/core/types.h"

namespace fleetmem::robot {

// Traces carry their code z, place p and domain; a learner pairs them by
// place and tells domains apart by name.
class Learner {
 public:
  virtual ~Learner() = default;
  // Learns from one segment: its new traces (`segment`, no rewards yet), the
  // segment's raw observations in the same order when the caller has them
  // (empty otherwise; only learners with a decoder use them), the traces
  // replayed from M_D for it (Eq. 19) and the rest of what the robot
  // remembers (M_D and the recalled traces of the segment's places).
  // Returns a one-line report (losses, pairs). An error stops the robot.
  virtual absl::StatusOr<std::string> Learn(
      std::span<const core::MemoryTrace> segment,
      std::span<const Observation> observations,
      std::span<const core::MemoryTrace> replayed,
      std::span<const core::MemoryTrace> memory) = 0;
  // R_ex (Eq. 11) of each of the segment's traces under the learner's own
  // model, after Learn. UNIMPLEMENTED (the default) makes the step use the
  // triplet loss in code space (rewards.h's ExternalRewards).
  virtual absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const core::MemoryTrace> /*segment*/,
      std::span<const core::MemoryTrace> /*memory*/) {
    return absl::UnimplementedError("no learned external reward");
  }
  // Unit descriptors of codes under the current model (what a map is
  // searched with). UNIMPLEMENTED (the default): the codes themselves.
  virtual absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> /*codes*/) {
    return absl::UnimplementedError("no learned descriptor");
  }
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_LEARNER_H_
