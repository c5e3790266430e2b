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

// Keeps at most `max_traces` of `traces` spread over the places and domains
// they cover (a merge of two clusters in forgetting, memory.md): greedy
// farthest-point selection, starting from the trace DownsampleByReward
// would keep first, each next pick the trace farthest from every kept one
// of its domain (planar distance of the places; a domain with no kept trace
// is infinitely far, so every domain keeps one trace before any keeps two);
// ties by reward, then as DownsampleByReward. Deterministic: the same traces
// in any order give the same survivors. Returns the dropped traces; `traces`
// keeps the survivors in selection order.
std::vector<MemoryTrace> DownsampleAlongPlaces(std::vector<MemoryTrace>& traces,
                                               int max_traces);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_DOWNSAMPLER_H_
