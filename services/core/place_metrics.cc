#include "services/core/place_metrics.h"

#include <cstddef>

namespace fleetmem::core {

double RecallAtK(const FirstCorrectRanks& ranks, int k) {
  if (ranks.empty()) return 0.0;
  size_t hits = 0;
  for (int rank : ranks) {
    if (rank >= 1 && rank <= k) ++hits;
  }
  return static_cast<double>(hits) / static_cast<double>(ranks.size());
}

double WeightedRecall(const FirstCorrectRanks& ranks) {
  double wr = 0.5 * RecallAtK(ranks, 1);
  for (int k = 2; k <= 6; ++k) wr += 0.1 * RecallAtK(ranks, k);
  return wr;
}

}  // namespace fleetmem::core
