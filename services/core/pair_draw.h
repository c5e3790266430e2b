// The pair-keeping refresh (issue 47), a draw beside Eq. 18's: the metric
// head a robot learns from its dynamic memory needs the same place seen in
// two domains (summer and winter), and Eq. 18's gamma^n * R favours hard
// traces, fewer of which have such a partner in the memory. This draw takes
// anchors in Eq. 18's order (successive sampling by gamma^n * R) and hands
// out each with its partner: the trace nearest the anchor's place among
// those of another domain within `radius` not drawn yet. An anchor without
// one goes alone. So every place of the memory held in two domains reaches
// the robot as a pair, with the paper's weights still choosing which.
#ifndef FLEETMEM_SERVICES_CORE_PAIR_DRAW_H_
#define FLEETMEM_SERVICES_CORE_PAIR_DRAW_H_

#include <cstddef>
#include <random>
#include <span>
#include <vector>

#include "services/core/types.h"

namespace fleetmem::core {

// Indices of up to `count` distinct `traces` in draw order (an anchor, then
// its partner). `weights[i]` is trace i's Eq. 18 weight. Places are
// compared by their Euclidean distance (x, y, z), domains by name.
// O(n log n) for n traces (a full successive-sampling order and a grid of
// the places with cells of `radius`).
std::vector<size_t> DrawPairs(std::span<const MemoryTrace* const> traces,
                              std::span<const double> weights, size_t count,
                              double radius, std::mt19937_64& rng);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_PAIR_DRAW_H_
