#include "services/core/downsampler.h"

#include <algorithm>
#include <cmath>
#include <iterator>
#include <limits>
#include <map>
#include <numeric>
#include <string>
#include <string_view>
#include <tuple>

namespace fleetmem::core {
namespace {

// True if `a` is kept in preference to `b`: higher reward (NaN lowest), then
// newer timestamp, then larger seq, then the larger robot id (a total
// order, so the survivors never depend on the input's order).
bool Preferred(const MemoryTrace& a, const MemoryTrace& b) {
  const bool a_nan = std::isnan(a.reward);
  const bool b_nan = std::isnan(b.reward);
  if (a_nan != b_nan) return b_nan;
  if (!a_nan && a.reward != b.reward) return a.reward > b.reward;
  return std::tie(a.timestamp_ns, a.seq, a.robot_id) >
         std::tie(b.timestamp_ns, b.seq, b.robot_id);
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

std::vector<MemoryTrace> DownsampleAlongPlaces(std::vector<MemoryTrace>& traces,
                                               int max_traces) {
  const size_t keep =
      std::min(traces.size(), static_cast<size_t>(std::max(max_traces, 0)));
  if (keep == traces.size()) return {};
  // Candidates in preference order: a strict comparison below then breaks
  // distance ties towards the preferred trace.
  std::vector<size_t> order(traces.size());
  std::iota(order.begin(), order.end(), size_t{0});
  std::stable_sort(order.begin(), order.end(), [&traces](size_t a, size_t b) {
    return Preferred(traces[a], traces[b]);
  });
  std::map<std::string_view, int> domain_ids;
  std::vector<int> domain(traces.size());
  for (size_t i = 0; i < traces.size(); ++i) {
    domain[i] =
        domain_ids
            .try_emplace(traces[i].domain, static_cast<int>(domain_ids.size()))
            .first->second;
  }
  // Distance from each candidate to the nearest kept trace of its domain.
  std::vector<double> nearest(traces.size(),
                              std::numeric_limits<double>::infinity());
  std::vector<bool> taken(traces.size(), false);
  std::vector<size_t> kept;
  kept.reserve(keep);
  while (kept.size() < keep) {
    size_t pick = traces.size();
    for (size_t i : order) {
      if (!taken[i] && (pick == traces.size() || nearest[i] > nearest[pick])) {
        pick = i;
      }
    }
    taken[pick] = true;
    kept.push_back(pick);
    const Place& at = traces[pick].place;
    for (size_t i = 0; i < traces.size(); ++i) {
      if (taken[i] || domain[i] != domain[pick]) continue;
      const Place& p = traces[i].place;
      nearest[i] = std::min(nearest[i], std::hypot(p.x - at.x, p.y - at.y));
    }
  }
  std::vector<MemoryTrace> survivors;
  survivors.reserve(keep);
  for (size_t i : kept) survivors.push_back(std::move(traces[i]));
  std::vector<MemoryTrace> dropped;
  dropped.reserve(traces.size() - keep);
  for (size_t i : order) {
    if (!taken[i]) dropped.push_back(std::move(traces[i]));
  }
  traces = std::move(survivors);
  return dropped;
}

}  // namespace fleetmem::core
