#include "clients/robot/runtime/fleet_recall.h"

#include <utility>
#include <vector>

#include "proto/convert/trace_convert.h"

namespace fleetmem::robot {

PlaceRecall NewFleetRecall(client::Client* client, std::string fleet_id,
                           double radius) {
  return [client, fleet_id = std::move(fleet_id), radius](
             const core::MemoryTrace& observed,
             size_t k) -> absl::StatusOr<std::vector<core::MemoryTrace>> {
    v1::QueryPlaceRequest request;
    request.set_fleet_id(fleet_id);
    request.mutable_code()->Add(observed.code.begin(), observed.code.end());
    request.set_k(static_cast<uint32_t>(k));
    api::PlaceToProto(observed.place, request.mutable_near());
    request.set_radius_m(radius);
    absl::StatusOr<std::vector<v1::PlaceMatch>> matches =
        client->QueryPlace(request);
    if (!matches.ok()) return matches.status();
    std::vector<core::MemoryTrace> recalled;
    for (const v1::PlaceMatch& m : *matches) {
      if (m.trace().code_size() != static_cast<int>(observed.code.size()))
        continue;
      recalled.push_back(api::TraceFromProto(m.trace()));
    }
    return recalled;
  };
}

absl::StatusOr<v1::UpdateRewardsResponse> SendRescored(
    client::Client& client, const std::string& fleet_id,
    std::span<const core::MemoryTrace> rescored, DynamicMemory& memory) {
  v1::UpdateRewardsRequest request;
  request.set_fleet_id(fleet_id);
  for (const core::MemoryTrace& t : rescored) {
    v1::RewardUpdate* update = request.add_updates();
    update->set_robot_id(t.robot_id);
    update->set_seq(t.seq);
    update->set_reward_external(t.reward_external);
    update->set_reward_internal(t.reward_internal);
    memory.SetRewards(t);
  }
  return client.UpdateRewards(request);
}

}  // namespace fleetmem::robot
