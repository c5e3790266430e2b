// fleetmem.v1 traces and places <-> the core's domain types, shared by the
// server's transport and the robot (so that neither keeps a copy). Pure
// functions; no validation (the engine validates domain values).
#ifndef FLEETMEM_PROTO_CONVERT_TRACE_CONVERT_H_
#define FLEETMEM_PROTO_CONVERT_TRACE_CONVERT_H_

#include <span>
#include <vector>

#include "fleetmem/v1/memory.pb.h"
#include "services/core/trace_filter.h"
#include "services/core/types.h"

namespace fleetmem::api {

core::Place PlaceFromProto(const v1::Pose& pose);
void PlaceToProto(const core::Place& place, v1::Pose* pose);

// Every field, including the server-set replay_count and cluster_id.
core::MemoryTrace TraceFromProto(const v1::MemoryTrace& trace);
void TraceToProto(const core::MemoryTrace& trace, v1::MemoryTrace* out);

// A DeleteTraces request's selection (its fleet_id aside), both ways.
core::TraceFilter FilterFromProto(const v1::DeleteTracesRequest& request);
core::ReadFilter ReadFilterFromProto(const v1::ReadFilter& filter);
void ReadFilterToProto(const core::ReadFilter& filter, v1::ReadFilter* out);
void FilterToProto(const core::TraceFilter& filter,
                   v1::DeleteTracesRequest* out);

// An UpdateRewards request's updates (its fleet_id aside), both ways.
std::vector<core::RewardUpdate> RewardUpdatesFromProto(
    const v1::UpdateRewardsRequest& request);
void RewardUpdatesToProto(std::span<const core::RewardUpdate> updates,
                          v1::UpdateRewardsRequest* out);

}  // namespace fleetmem::api

#endif  // FLEETMEM_PROTO_CONVERT_TRACE_CONVERT_H_
