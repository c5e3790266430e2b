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

}  // namespace fleetmem::api
