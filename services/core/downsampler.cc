#include "services/core/downsampler.h"

#include <algorithm>
#include <cmath>
#include <iterator>
#include <tuple>

namespace fleetmem::core {
namespace {

// True if `a` is kept in preference to `b`: higher reward (NaN lowest), then
// newer timestamp, then larger seq.
bool Preferred(const MemoryTrace& a, const MemoryTrace& b) {
  const bool a_nan = std::isnan(a.reward);
  const bool b_nan = std::isnan(b.reward);
  if (a_nan != b_nan) return b_nan;
  if (!a_nan && a.reward != b.reward) return a.reward > b.reward;
  return std::tie(a.timestamp_ns, a.seq) > std::tie(b.timestamp_ns, b.seq);
}

}  // namespace

std::vector<MemoryTrace> DownsampleByReward(std::vector<MemoryTrace>& traces,
                                            int max_traces) {
  std::stable_sort(traces.begin(), traces.end(), Preferred);
  const size_t keep =
      std::min(traces.size(), static_cast<size_t>(std::max(max_traces, 0)));
  std::vector<MemoryTrace> dropped(
      std::make_move_iterator(traces.begin() + keep),
      std::make_move_iterator(traces.end()));
  traces.resize(keep);
  return dropped;
}

}  // namespace fleetmem::core
