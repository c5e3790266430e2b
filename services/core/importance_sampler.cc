#include "services/core/importance_sampler.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <numeric>

namespace fleetmem::core {
namespace {

// Uniform in (0, 1), never 0 (log(0) would tie every such key at -inf); the
// same on every standard library.
double UniformOpen01(std::mt19937_64& rng) {
  return (static_cast<double>(rng() >> 11) + 0.5) * 0x1.0p-53;
}

struct Key {
  bool positive = false;  // positive-weight items come first
  double value = 0.0;     // log(u) / w; larger is drawn earlier
  size_t index = 0;
};

bool DrawnBefore(const Key& a, const Key& b) {
  if (a.positive != b.positive) return a.positive;
  if (a.value != b.value) return a.value > b.value;
  return a.index < b.index;
}

}  // namespace

double ReplayWeight(float reward, uint32_t replay_count, double gamma,
                    double reward_floor) {
  const double r = std::isnan(reward)
                       ? reward_floor
                       : std::max(static_cast<double>(reward), reward_floor);
  return std::pow(gamma, static_cast<double>(replay_count)) * r;
}

std::vector<size_t> SampleWithoutReplacement(std::span<const double> weights,
                                             size_t count,
                                             std::mt19937_64& rng) {
  const size_t n = weights.size();
  count = std::min(count, n);
  if (count == 0) return {};

  // Efraimidis-Spirakis: key u^(1/w), kept as log(u)/w so that tiny weights
  // do not underflow every key to 0. Sorting by key descending gives the
  // draw order of successive sampling. Non-positive (and NaN) weights get a
  // uniform key in a lower tier: drawn last, in random order.
  std::vector<Key> keys(n);
  for (size_t i = 0; i < n; ++i) {
    const double log_u = std::log(UniformOpen01(rng));
    const double w = weights[i];
    keys[i].index = i;
    if (w > 0.0) {
      keys[i].positive = true;
      keys[i].value = std::isinf(w) ? 0.0 : log_u / w;
    } else {
      keys[i].value = log_u;
    }
  }
  std::partial_sort(keys.begin(), keys.begin() + count, keys.end(),
                    DrawnBefore);
  std::vector<size_t> drawn(count);
  for (size_t i = 0; i < count; ++i) drawn[i] = keys[i].index;
  return drawn;
}

}  // namespace fleetmem::core
