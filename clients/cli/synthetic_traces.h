// Synthetic memory traces for docs, demos and smoke tests (not real data).
//
// Every robot drives the same closed loop of `per_robot` places, 5 m apart,
// in its own appearance domain (summer, fall, winter, spring, in turn).
// A trace's code is the place's prototype (varying smoothly along the loop)
// plus a domain shift and noise, L2-normalised, so the same place seen by two
// robots has nearby codes and a query with one finds the other. Positions get
// 1 m of noise; rewards are random (external in [0, 1), internal in
// [0, 0.5)). Deterministic for a given seed and build.
#ifndef FLEETMEM_CLIENTS_CLI_SYNTHETIC_TRACES_H_
#define FLEETMEM_CLIENTS_CLI_SYNTHETIC_TRACES_H_

#include <cstdint>
#include <string>
#include <vector>

#include "fleetmem/v1/memory.pb.h"

namespace fleetmem::cli {

struct SyntheticTraceOptions {
  // Robots, named robot-1 .. robot-N.
  int robots = 3;
  // Traces per robot, seq 1 .. per_robot, one per place of the loop.
  int per_robot = 100;
  // Code dimension.
  int dimension = 256;
  // Seed of the random generator.
  uint64_t seed = 1;
  // encoder_version of every trace.
  std::string encoder_version = "v1";
};

// robots * per_robot traces, robot by robot, in seq order. Non-positive
// counts give no traces.
std::vector<v1::MemoryTrace> GenerateSyntheticTraces(
    const SyntheticTraceOptions& options);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_SYNTHETIC_TRACES_H_
