#include "proto/convert/trace_convert.h"

namespace fleetmem::api {

core::Place PlaceFromProto(const v1::Pose& pose) {
  return core::Place{
      .x = pose.x(), .y = pose.y(), .z = pose.z(), .yaw = pose.yaw()};
}

void PlaceToProto(const core::Place& place, v1::Pose* pose) {
  pose->set_x(place.x);
  pose->set_y(place.y);
  pose->set_z(place.z);
  pose->set_yaw(place.yaw);
}

core::MemoryTrace TraceFromProto(const v1::MemoryTrace& trace) {
  core::MemoryTrace out;
  out.robot_id = trace.robot_id();
  out.seq = trace.seq();
  out.domain = trace.domain();
  out.code.assign(trace.code().begin(), trace.code().end());
  out.place = PlaceFromProto(trace.pose());
  out.reward = trace.reward();
  out.reward_external = trace.reward_external();
  out.reward_internal = trace.reward_internal();
  out.timestamp_ns = trace.timestamp_ns();
  out.replay_count = trace.replay_count();
  out.encoder_version = trace.encoder_version();
  out.cluster_id = trace.cluster_id();
  out.attachment = trace.attachment();
  return out;
}

void TraceToProto(const core::MemoryTrace& trace, v1::MemoryTrace* out) {
  out->set_robot_id(trace.robot_id);
  out->set_seq(trace.seq);
  out->set_domain(trace.domain);
  out->mutable_code()->Assign(trace.code.begin(), trace.code.end());
  PlaceToProto(trace.place, out->mutable_pose());
  out->set_reward(trace.reward);
  out->set_reward_external(trace.reward_external);
  out->set_reward_internal(trace.reward_internal);
  out->set_timestamp_ns(trace.timestamp_ns);
  out->set_replay_count(trace.replay_count);
  out->set_encoder_version(trace.encoder_version);
  out->set_cluster_id(trace.cluster_id);
  out->set_attachment(trace.attachment);
}

core::ReadFilter ReadFilterFromProto(const v1::ReadFilter& filter) {
  core::ReadFilter out;
  out.robot_ids.assign(filter.robot_ids().begin(), filter.robot_ids().end());
  out.domains.assign(filter.domains().begin(), filter.domains().end());
  if (filter.has_time_from_ns()) out.time_from_ns = filter.time_from_ns();
  if (filter.has_time_to_ns()) out.time_to_ns = filter.time_to_ns();
  out.encoder_version = filter.encoder_version();
  return out;
}

void ReadFilterToProto(const core::ReadFilter& filter, v1::ReadFilter* out) {
  for (const std::string& robot_id : filter.robot_ids) {
    out->add_robot_ids(robot_id);
  }
  for (const std::string& domain : filter.domains) out->add_domains(domain);
  if (filter.time_from_ns) out->set_time_from_ns(*filter.time_from_ns);
  if (filter.time_to_ns) out->set_time_to_ns(*filter.time_to_ns);
  out->set_encoder_version(filter.encoder_version);
}

core::TraceFilter FilterFromProto(const v1::DeleteTracesRequest& request) {
  core::TraceFilter filter;
  filter.robot_id = request.robot_id();
  filter.domain = request.domain();
  if (request.has_seq_first()) filter.seq_first = request.seq_first();
  if (request.has_seq_last()) filter.seq_last = request.seq_last();
  if (request.has_time_from_ns()) filter.time_from_ns = request.time_from_ns();
  if (request.has_time_to_ns()) filter.time_to_ns = request.time_to_ns();
  return filter;
}

void FilterToProto(const core::TraceFilter& filter,
                   v1::DeleteTracesRequest* out) {
  out->set_robot_id(filter.robot_id);
  out->set_domain(filter.domain);
  if (filter.seq_first) out->set_seq_first(*filter.seq_first);
  if (filter.seq_last) out->set_seq_last(*filter.seq_last);
  if (filter.time_from_ns) out->set_time_from_ns(*filter.time_from_ns);
  if (filter.time_to_ns) out->set_time_to_ns(*filter.time_to_ns);
}

std::vector<core::RewardUpdate> RewardUpdatesFromProto(
    const v1::UpdateRewardsRequest& request) {
  std::vector<core::RewardUpdate> updates;
  updates.reserve(request.updates_size());
  for (const v1::RewardUpdate& update : request.updates()) {
    updates.push_back(
        core::RewardUpdate{core::TraceKey{update.robot_id(), update.seq()},
                           update.reward_external(), update.reward_internal()});
  }
  return updates;
}

void RewardUpdatesToProto(std::span<const core::RewardUpdate> updates,
                          v1::UpdateRewardsRequest* out) {
  for (const core::RewardUpdate& update : updates) {
    v1::RewardUpdate* one = out->add_updates();
    one->set_robot_id(update.key.robot_id);
    one->set_seq(update.key.seq);
    one->set_reward_external(update.reward_external);
    one->set_reward_internal(update.reward_internal);
  }
}

}  // namespace fleetmem::api
