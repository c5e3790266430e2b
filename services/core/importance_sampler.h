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

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_IMPORTANCE_SAMPLER_H_
