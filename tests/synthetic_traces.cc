#include "tests/synthetic_traces.h"

#include <random>

namespace fleetmem::testing {

uint64_t StableHash(const std::string& text) {
  uint64_t hash = 1469598103934665603ull;
  for (unsigned char c : text) {
    hash ^= c;
    hash *= 1099511628211ull;
  }
  return hash;
}

std::vector<float> RandomCode(uint64_t seed, const std::string& robot_id,
                              uint64_t seq, size_t dimension) {
  std::seed_seq seeds{static_cast<uint32_t>(seed),
                      static_cast<uint32_t>(seed >> 32),
                      static_cast<uint32_t>(StableHash(robot_id)),
                      static_cast<uint32_t>(StableHash(robot_id) >> 32),
                      static_cast<uint32_t>(seq),
                      static_cast<uint32_t>(seq >> 32)};
  std::mt19937_64 rng(seeds);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::vector<float> code(dimension);
  for (float& value : code) value = normal(rng);
  return code;
}

v1::Pose RoutePose(const std::string& robot_id, uint64_t seq, double step_m) {
  v1::Pose pose;
  pose.set_x(static_cast<double>(seq) * step_m);
  pose.set_y(static_cast<double>(StableHash(robot_id) % 1000) * 1000.0);
  pose.set_z(0.0);
  pose.set_yaw(0.0);
  return pose;
}

v1::MemoryTrace MakeTrace(const TraceSpec& spec, uint64_t seq) {
  v1::MemoryTrace trace;
  trace.set_robot_id(spec.robot_id);
  trace.set_seq(seq);
  trace.set_domain(spec.domain);
  for (float value :
       RandomCode(spec.seed, spec.robot_id, seq, spec.dimension)) {
    trace.add_code(value);
  }
  *trace.mutable_pose() = RoutePose(spec.robot_id, seq, spec.step_m);
  const float reward = spec.reward ? spec.reward(seq) : 0.5f;
  trace.set_reward(reward);
  trace.set_reward_external(reward * 0.75f);
  trace.set_reward_internal(reward * 0.25f);
  trace.set_timestamp_ns(1'700'000'000'000'000'000 +
                         static_cast<int64_t>(seq) * 100'000'000);
  trace.set_encoder_version(spec.encoder_version);
  return trace;
}

std::vector<v1::MemoryTrace> MakeTraces(const TraceSpec& spec) {
  std::vector<v1::MemoryTrace> traces;
  traces.reserve(spec.count);
  for (uint64_t i = 0; i < spec.count; ++i) {
    traces.push_back(MakeTrace(spec, spec.first_seq + i));
  }
  return traces;
}

v1::UploadTracesRequest MakeUploadRequest(
    const std::string& fleet_id, std::span<const v1::MemoryTrace> traces) {
  v1::UploadTracesRequest request;
  request.set_fleet_id(fleet_id);
  for (const v1::MemoryTrace& trace : traces) *request.add_traces() = trace;
  return request;
}

std::vector<v1::UploadTracesRequest> MakeUploadRequests(
    const std::string& fleet_id, std::span<const v1::MemoryTrace> traces,
    size_t batch) {
  if (batch == 0) batch = 1;
  std::vector<v1::UploadTracesRequest> requests;
  for (size_t begin = 0; begin < traces.size(); begin += batch) {
    const size_t size = std::min(batch, traces.size() - begin);
    requests.push_back(
        MakeUploadRequest(fleet_id, traces.subspan(begin, size)));
  }
  return requests;
}

}  // namespace fleetmem::testing
