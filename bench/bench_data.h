// Synthetic memory traces for the scale benchmarks: 256-d codes of low
// intrinsic dimension (a 16-d gaussian latent through a fixed random map,
// plus isotropic noise, normalised — learned place descriptors are far from
// uniform on the sphere) observed along a route (places 1 m apart, a random
// walk in heading). Deterministic in the seed.
#ifndef FLEETMEM_BENCH_BENCH_DATA_H_
#define FLEETMEM_BENCH_BENCH_DATA_H_

#include <cmath>
#include <cstdint>
#include <random>
#include <string>
#include <vector>

#include "services/core/types.h"

namespace fleetmem::bench {

class CodeSource {
 public:
  static constexpr size_t kLatent = 16;

  CodeSource(size_t dimension, uint64_t seed) : rng_(seed) {
    std::normal_distribution<float> normal(0.0f, 1.0f);
    map_.resize(dimension * kLatent);
    for (float& x : map_) x = normal(rng_);
  }
  size_t dimension() const { return map_.size() / kLatent; }

  std::vector<float> Next() {
    std::normal_distribution<float> normal(0.0f, 1.0f);
    float z[kLatent];
    for (float& x : z) x = normal(rng_);
    std::vector<float> v(dimension());
    double norm = 0.0;
    for (size_t i = 0; i < v.size(); ++i) {
      float dot = 0.05f * normal(rng_);
      for (size_t j = 0; j < kLatent; ++j) dot += map_[i * kLatent + j] * z[j];
      v[i] = dot;
      norm += double{dot} * dot;
    }
    const float scale = static_cast<float>(1.0 / std::sqrt(norm));
    for (float& x : v) x *= scale;
    return v;
  }

  // Trace `seq` of `robot`: a code, the next place of the route, a reward.
  core::MemoryTrace NextTrace(const std::string& robot, uint64_t seq) {
    std::uniform_real_distribution<double> turn(-0.2, 0.2);
    std::uniform_real_distribution<float> reward(0.0f, 2.0f);
    heading_ += turn(rng_);
    x_ += std::cos(heading_);
    y_ += std::sin(heading_);
    core::MemoryTrace trace;
    trace.robot_id = robot;
    trace.seq = seq;
    trace.domain = seq % 2 == 0 ? "summer" : "winter";
    trace.code = Next();
    trace.place = core::Place{x_, y_, 0.0, heading_};
    trace.reward = reward(rng_);
    trace.encoder_version = "bench";
    return trace;
  }

 private:
  std::mt19937_64 rng_;
  std::vector<float> map_;
  double x_ = 0.0, y_ = 0.0, heading_ = 0.0;
};

}  // namespace fleetmem::bench

#endif  // FLEETMEM_BENCH_BENCH_DATA_H_
