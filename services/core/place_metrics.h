// Place-recognition metrics (memory.md "Metrics"; BioSLAM Sec. VI).
#ifndef FLEETMEM_SERVICES_CORE_PLACE_METRICS_H_
#define FLEETMEM_SERVICES_CORE_PLACE_METRICS_H_

#include <array>
#include <vector>

namespace fleetmem::core {

// For each query, the 1-based rank of its first correct match among the
// retrieved references, or 0 if none was correct.
using FirstCorrectRanks = std::vector<int>;

// Recall@k: share of queries whose first correct match has rank <= k.
// 0 for no queries.
double RecallAtK(const FirstCorrectRanks& ranks, int k);

// WR = 0.5 r_1 + 0.1 (r_2 + ... + r_6).
double WeightedRecall(const FirstCorrectRanks& ranks);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_PLACE_METRICS_H_
