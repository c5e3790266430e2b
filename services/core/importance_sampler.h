// Importance sampling without replacement (Eqs. 18-19), weight
// w_k = gamma^{n_k} * max(R_k, floor).
#ifndef FLEETMEM_SERVICES_CORE_IMPORTANCE_SAMPLER_H_
#define FLEETMEM_SERVICES_CORE_IMPORTANCE_SAMPLER_H_

#include <cstdint>
#include <random>
#include <span>
#include <vector>

namespace fleetmem::core {

// w = gamma^replay_count * max(reward, reward_floor). NaN rewards count as
// the floor.
double ReplayWeight(float reward, uint32_t replay_count, double gamma,
                    double reward_floor);

// Draws min(count, n) distinct indices of `weights`, each draw proportional
// to the weights of the items not drawn yet (successive sampling, done in
// O(n log count) by Efraimidis-Spirakis keys u^(1/w)). Items of weight <= 0
// are drawn only after every positive-weight item. Order: draw order.
std::vector<size_t> SampleWithoutReplacement(std::span<const double> weights,
                                             size_t count,
                                             std::mt19937_64& rng);

// Successive sampling without replacement from weights that change a few at a
// time (the static memory's replay weights), in time sublinear in the number
// of items: a sum tree over the weights, as prioritized experience replay
// keeps (Schaul et al. 2016). Set/Clear are O(log n); drawing c items is
// O(c log n). Draws have the distribution of SampleWithoutReplacement: each
// draw picks a not-yet-drawn positive-weight item with probability
// proportional to its weight; once none is left, items of weight <= 0 (or
// NaN) are drawn uniformly. Slots are small integers chosen by the caller.
class WeightedSampler {
 public:
  // Makes `slot` drawable with `weight` (growing the slots as needed).
  void Set(size_t slot, double weight);
  // Makes `slot` not drawable.
  void Clear(size_t slot);
  // On an empty sampler: Set(i, weights[i]) for every i, in O(n) rather
  // than O(n log n) (a restart restores every trace at once: 10,000,000 of
  // them took two walks of 24 levels each). The trees come out as the
  // calls would leave them, so later draws are the same.
  void SetAll(std::span<const double> weights);
  // Drawable slots.
  size_t size() const { return size_; }
  // Draws min(count, size()) distinct slots in draw order; the weights are
  // unchanged afterwards.
  std::vector<size_t> Draw(size_t count, std::mt19937_64& rng);

 private:
  // Sums over a complete binary tree whose leaves are the slots; a parent is
  // recomputed from its two children on every change, so no rounding drift
  // accumulates and a tree of zero leaves sums to exactly 0.
  class SumTree {
   public:
    void Set(size_t slot, double value);
    // On an empty tree: Set(i, values[i]) for each non-zero value.
    void Assign(std::span<const double> values);
    double Get(size_t slot) const;
    double Total() const { return nodes_.size() > 1 ? nodes_[1] : 0.0; }
    // The leaf where the running sum first exceeds `target` (0 <= target <
    // Total()); never a leaf of value 0.
    size_t Find(double target) const;

   private:
    size_t leaves_ = 0;  // a power of two
    std::vector<double>
        nodes_;  // 1-based heap layout: leaves at [leaves_, 2 leaves_)
  };

  SumTree positive_;  // slots of positive weight
  SumTree zero_;      // 1 for drawable slots of weight <= 0 or NaN
  size_t size_ = 0;
};

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_IMPORTANCE_SAMPLER_H_
