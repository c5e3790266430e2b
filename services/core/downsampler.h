// Downsampling within a cluster (Eq. 15). memory.md decision: keep the traces
// with the highest reward (hard samples), ties to the newest.
#ifndef FLEETMEM_SERVICES_CORE_DOWNSAMPLER_H_
#define FLEETMEM_SERVICES_CORE_DOWNSAMPLER_H_

#include <vector>

#include "services/core/types.h"

namespace fleetmem::core {

// Splits `traces` into the at most `max_traces` kept (highest reward first;
// equal rewards: larger timestamp_ns, then larger seq, wins) and the rest.
// Returns the dropped traces; `traces` keeps the survivors.
std::vector<MemoryTrace> DownsampleByReward(std::vector<MemoryTrace>& traces,
                                            int max_traces);
// The same over `positions` into `traces`: `positions` keeps the survivors'
// positions in the order above; returns the dropped ones'.
std::vector<size_t> DownsampleByReward(const std::vector<MemoryTrace>& traces,
                                       std::vector<size_t>& positions,
                                       int max_traces);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_DOWNSAMPLER_H_
