#include "services/core/pair_draw.h"

#include <cmath>
#include <cstdint>
#include <limits>
#include <utility>

#include "absl/container/flat_hash_map.h"
#include "services/core/importance_sampler.h"

namespace fleetmem::core {
namespace {

using Cell = std::pair<int64_t, int64_t>;

Cell CellOf(const Place& place, double radius) {
  return {static_cast<int64_t>(std::floor(place.x / radius)),
          static_cast<int64_t>(std::floor(place.y / radius))};
}

double Distance(const Place& a, const Place& b) {
  return std::sqrt((a.x - b.x) * (a.x - b.x) + (a.y - b.y) * (a.y - b.y) +
                   (a.z - b.z) * (a.z - b.z));
}

}  // namespace

std::vector<size_t> DrawPairs(std::span<const MemoryTrace* const> traces,
                              std::span<const double> weights, size_t count,
                              double radius, std::mt19937_64& rng) {
  const size_t n = traces.size();
  count = std::min(count, n);
  std::vector<size_t> out;
  if (count == 0) return out;
  out.reserve(count);
  const std::vector<size_t> order = SampleWithoutReplacement(weights, n, rng);
  const bool pairs = radius > 0.0 && std::isfinite(radius);
  absl::flat_hash_map<Cell, std::vector<size_t>> grid;
  if (pairs) {
    for (size_t i = 0; i < n; ++i) {
      grid[CellOf(traces[i]->place, radius)].push_back(i);
    }
  }
  std::vector<bool> taken(n, false);
  for (size_t anchor : order) {
    if (out.size() >= count) break;
    if (taken[anchor]) continue;
    taken[anchor] = true;
    out.push_back(anchor);
    if (!pairs || out.size() >= count) continue;
    const MemoryTrace& a = *traces[anchor];
    const auto [cx, cy] = CellOf(a.place, radius);
    size_t partner = n;
    double nearest = std::numeric_limits<double>::infinity();
    for (int64_t dx = -1; dx <= 1; ++dx) {
      for (int64_t dy = -1; dy <= 1; ++dy) {
        auto cell = grid.find(Cell{cx + dx, cy + dy});
        if (cell == grid.end()) continue;
        for (size_t j : cell->second) {
          if (taken[j] || traces[j]->domain == a.domain) continue;
          const double d = Distance(traces[j]->place, a.place);
          // Ties: the lower index (the caller's order), for repeatable draws.
          if (d <= radius && (d < nearest || (d == nearest && j < partner))) {
            nearest = d;
            partner = j;
          }
        }
      }
    }
    if (partner < n) {
      taken[partner] = true;
      out.push_back(partner);
    }
  }
  return out;
}

}  // namespace fleetmem::core
