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

// A positive weight as the sum tree holds it: an infinite weight is drawn
// first among finite ones; the sums stay finite.
double Capped(double weight) {
  return std::min(weight, std::numeric_limits<double>::max() / (1ull << 40));
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

void WeightedSampler::SumTree::Set(size_t slot, double value) {
  if (slot >= leaves_) {
    size_t leaves = std::max<size_t>(leaves_, 16);
    while (leaves <= slot) leaves *= 2;
    std::vector<double> nodes(2 * leaves, 0.0);
    for (size_t i = 0; i < leaves_; ++i)
      nodes[leaves + i] = nodes_[leaves_ + i];
    for (size_t i = leaves - 1; i >= 1; --i) {
      nodes[i] = nodes[2 * i] + nodes[2 * i + 1];
    }
    leaves_ = leaves;
    nodes_ = std::move(nodes);
  }
  size_t node = leaves_ + slot;
  nodes_[node] = value;
  for (node /= 2; node >= 1; node /= 2) {
    nodes_[node] = nodes_[2 * node] + nodes_[2 * node + 1];
  }
}

void WeightedSampler::SumTree::Assign(std::span<const double> values) {
  size_t used = values.size();
  while (used > 0 && values[used - 1] == 0.0) --used;
  if (used == 0) return;  // Set(i, 0) on an empty tree leaves it so
  // As Set grows the tree for its largest slot, used - 1.
  size_t leaves = std::max<size_t>(leaves_, 16);
  while (leaves < used) leaves *= 2;
  nodes_.assign(2 * leaves, 0.0);
  std::copy(values.begin(), values.begin() + used, nodes_.begin() + leaves);
  for (size_t i = leaves - 1; i >= 1; --i) {
    nodes_[i] = nodes_[2 * i] + nodes_[2 * i + 1];
  }
  leaves_ = leaves;
}

double WeightedSampler::SumTree::Get(size_t slot) const {
  return slot < leaves_ ? nodes_[leaves_ + slot] : 0.0;
}

size_t WeightedSampler::SumTree::Find(double target) const {
  size_t node = 1;
  while (node < leaves_) {
    const double left = nodes_[2 * node];
    const double right = nodes_[2 * node + 1];
    // Rounding can leave `target` at or past the left sum when the right
    // subtree is empty: stay on the side that holds weight.
    if ((target < left && left > 0.0) || right <= 0.0) {
      node = 2 * node;
    } else {
      target -= left;
      node = 2 * node + 1;
    }
  }
  return node - leaves_;
}

void WeightedSampler::Set(size_t slot, double weight) {
  const bool was = positive_.Get(slot) > 0.0 || zero_.Get(slot) > 0.0;
  if (weight > 0.0) {
    positive_.Set(slot, Capped(weight));
    if (zero_.Get(slot) > 0.0) zero_.Set(slot, 0.0);
  } else {
    zero_.Set(slot, 1.0);
    if (positive_.Get(slot) > 0.0) positive_.Set(slot, 0.0);
  }
  if (!was) ++size_;
}

void WeightedSampler::SetAll(std::span<const double> weights) {
  if (size_ != 0 || positive_.Total() != 0.0 || zero_.Total() != 0.0) {
    for (size_t i = 0; i < weights.size(); ++i) Set(i, weights[i]);
    return;
  }
  std::vector<double> positive(weights.size(), 0.0);
  std::vector<double> zero(weights.size(), 0.0);
  for (size_t i = 0; i < weights.size(); ++i) {
    // As Set does.
    if (weights[i] > 0.0) {
      positive[i] = Capped(weights[i]);
    } else {
      zero[i] = 1.0;
    }
  }
  positive_.Assign(positive);
  zero_.Assign(zero);
  size_ = weights.size();
}

void WeightedSampler::Clear(size_t slot) {
  const bool was = positive_.Get(slot) > 0.0 || zero_.Get(slot) > 0.0;
  if (positive_.Get(slot) > 0.0) positive_.Set(slot, 0.0);
  if (zero_.Get(slot) > 0.0) zero_.Set(slot, 0.0);
  if (was) --size_;
}

std::vector<size_t> WeightedSampler::Draw(size_t count, std::mt19937_64& rng) {
  count = std::min(count, size_);
  std::vector<size_t> drawn;
  drawn.reserve(count);
  // Drawn slots leave their tree until the end (without replacement).
  std::vector<std::pair<size_t, double>> taken_positive;
  std::vector<size_t> taken_zero;
  while (drawn.size() < count) {
    SumTree& tree = positive_.Total() > 0.0 ? positive_ : zero_;
    const double total = tree.Total();
    if (total <= 0.0) break;
    const size_t slot = tree.Find(UniformOpen01(rng) * total);
    if (&tree == &positive_) {
      taken_positive.emplace_back(slot, tree.Get(slot));
    } else {
      taken_zero.push_back(slot);
    }
    tree.Set(slot, 0.0);
    drawn.push_back(slot);
  }
  for (const auto& [slot, weight] : taken_positive) positive_.Set(slot, weight);
  for (size_t slot : taken_zero) zero_.Set(slot, 1.0);
  return drawn;
}

}  // namespace fleetmem::core
