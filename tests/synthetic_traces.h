// Synthetic memory traces for the integration tests: deterministic codes,
// places along a per-robot route and chosen rewards, as proto messages.
#ifndef FLEETMEM_TESTS_SYNTHETIC_TRACES_H_
#define FLEETMEM_TESTS_SYNTHETIC_TRACES_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <span>
#include <string>
#include <vector>

#include "fleetmem/v1/memory.pb.h"

namespace fleetmem::testing {

// What MakeTraces generates. A trace is a pure function of (seed, robot_id,
// seq, dimension, ...): the same spec always yields the same traces, so a
// retried upload resends identical messages.
struct TraceSpec {
  // Robot that "observed" the traces.
  std::string robot_id = "robot-1";
  // Sequence number of the first trace; the others follow one by one.
  uint64_t first_seq = 1;
  // Number of traces.
  size_t count = 1;
  // Code dimension D.
  size_t dimension = 32;
  // Appearance domain of every trace.
  std::string domain = "summer";
  // Encoder version of every trace.
  std::string encoder_version = "enc-v1";
  // Reward of the trace with sequence number `seq`; empty means 0.5.
  std::function<float(uint64_t seq)> reward = nullptr;
  // Metres between consecutive traces along the robot's route (the x axis;
  // each robot drives its own lane of y, 1 km apart).
  double step_m = 5.0;
  // Mixed into every code.
  uint64_t seed = 1;
};

// Traces first_seq .. first_seq + count - 1 of `spec`.
std::vector<v1::MemoryTrace> MakeTraces(const TraceSpec& spec);

// The trace with sequence number `seq` of `spec` (ignores first_seq/count).
v1::MemoryTrace MakeTrace(const TraceSpec& spec, uint64_t seq);

// A code of independent standard normal values, a pure function of the
// arguments.
std::vector<float> RandomCode(uint64_t seed, const std::string& robot_id,
                              uint64_t seq, size_t dimension);

// Place of trace `seq` of `robot_id`: x = seq * step_m, y = lane * 1000,
// z = 0, where lane is a stable number derived from the robot id.
v1::Pose RoutePose(const std::string& robot_id, uint64_t seq, double step_m);

// One upload message with all of `traces`.
v1::UploadTracesRequest MakeUploadRequest(
    const std::string& fleet_id, std::span<const v1::MemoryTrace> traces);

// `traces` cut into messages of at most `batch` traces (batch >= 1).
std::vector<v1::UploadTracesRequest> MakeUploadRequests(
    const std::string& fleet_id, std::span<const v1::MemoryTrace> traces,
    size_t batch);

// Stable 64-bit FNV-1a hash of `text` (for seeds and lanes).
uint64_t StableHash(const std::string& text);

}  // namespace fleetmem::testing

#endif  // FLEETMEM_TESTS_SYNTHETIC_TRACES_H_
