// The place recall of the segment step (segment_step.h) against a fleet's
// memory: for an observation, QueryPlace with its code, k and its place as
// the position prior within `radius` (place units). Used by the robot's
// agent and by fleetmem-eval lifelong, so that both recall the same way.
#ifndef FLEETMEM_CLIENTS_ROBOT_RUNTIME_FLEET_RECALL_H_
#define FLEETMEM_CLIENTS_ROBOT_RUNTIME_FLEET_RECALL_H_

#include <string>

#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/runtime/segment_step.h"

namespace fleetmem::robot {

// Recalls through `client` (which must outlive the recall). The server's
// errors come back as they are (NOT_FOUND: the fleet has no memory yet);
// matches whose code has another dimension than the observation's (another
// encoder's traces) are left out.
PlaceRecall NewFleetRecall(client::Client* client, std::string fleet_id,
                           double radius);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_RUNTIME_FLEET_RECALL_H_
