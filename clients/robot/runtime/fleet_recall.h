// The segment step's (segment_step.h) calls to a fleet's memory: its place
// recall (for an observation, QueryPlace with its code, k and its place as
// the position prior within `radius`, place units) and the re-scored
// remembered traces sent back. Used by the robot's agent and by
// fleetmem-eval lifelong, so that both do them the same way.
#ifndef FLEETMEM_CLIENTS_ROBOT_RUNTIME_FLEET_RECALL_H_
#define FLEETMEM_CLIENTS_ROBOT_RUNTIME_FLEET_RECALL_H_

#include <span>
#include <string>

#include "absl/status/statusor.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/memory/dynamic_memory.h"
#include "clients/robot/runtime/segment_step.h"

namespace fleetmem::robot {

// Recalls through `client` (which must outlive the recall). The server's
// errors come back as they are (NOT_FOUND: the fleet has no memory yet);
// matches whose code has another dimension than the observation's (another
// encoder's traces) are left out.
PlaceRecall NewFleetRecall(client::Client* client, std::string fleet_id,
                           double radius);

// The step's re-scored remembered traces (SegmentStepResult::rescored):
// their new R in `memory` (M_D keeps each entry's place and replay count),
// and their R_ex and R_in to the fleet by one UpdateRewards through
// `client`. The fleet's answer, or its error.
absl::StatusOr<v1::UpdateRewardsResponse> SendRescored(
    client::Client& client, const std::string& fleet_id,
    std::span<const core::MemoryTrace> rescored, DynamicMemory& memory);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_RUNTIME_FLEET_RECALL_H_
