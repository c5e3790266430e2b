// A hook on each observation of an uploading robot, between its encoding
// and the record of its trace: the interface the agent
// (clients/robot/runtime/agent.h) calls and the SLAM back end
// (clients/robot/slam/fleet_slam.h) implements. Here, below both, so that
// the SLAM module does not include the runtime's headers.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_HOOK_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_HOOK_H_

#include <cstddef>
#include <span>

#include "absl/status/status.h"
#include "clients/robot/sensing/observation.h"
#include "fleetmem/v1/memory.pb.h"

namespace fleetmem::robot {

// Sees every observation of an uploading robot after it is encoded and
// before its trace is recorded, and may change that trace: the SLAM back end
// puts its pose estimate in `trace.pose` and the keyframe's scan in
// `trace.attachment`. Called from the agent's loop in source order, from the
// index the robot starts or resumes at. An error stops the robot (nothing of
// that observation is recorded).
class ObservationHook {
 public:
  virtual ~ObservationHook() = default;
  virtual absl::Status BeforeRecord(size_t index,
                                    const Observation& observation,
                                    std::span<const float> code,
                                    v1::MemoryTrace& trace) = 0;
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_HOOK_H_
