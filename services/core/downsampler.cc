#include "services/core/downsampler.h"

#include <algorithm>
#include <cmath>
#include <iterator>
#include <numeric>
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

std::vector<size_t> DownsampleByReward(const std::vector<MemoryTrace>& traces,
                                       std::vector<size_t>& positions,
                                       int max_traces) {
  std::stable_sort(positions.begin(), positions.end(),
                   [&traces](size_t a, size_t b) {
                     return Preferred(traces[a], traces[b]);
                   });
  const size_t keep =
      std::min(positions.size(), static_cast<size_t>(std::max(max_traces, 0)));
  std::vector<size_t> dropped(positions.begin() + keep, positions.end());
  positions.resize(keep);
  return dropped;
}

std::vector<MemoryTrace> DownsampleByReward(std::vector<MemoryTrace>& traces,
                                            int max_traces) {
  std::vector<size_t> kept(traces.size());
  std::iota(kept.begin(), kept.end(), size_t{0});
  const std::vector<size_t> dropped =
      DownsampleByReward(traces, kept, max_traces);
  std::vector<MemoryTrace> survivors;
  survivors.reserve(kept.size());
  for (size_t i : kept) survivors.push_back(std::move(traces[i]));
  std::vector<MemoryTrace> out;
  out.reserve(dropped.size());
  for (size_t i : dropped) out.push_back(std::move(traces[i]));
  traces = std::move(survivors);
  return out;
}

}  // namespace fleetmem::core
