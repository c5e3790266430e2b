// Triplet selection for the GPL place head (BioSLAM Eq. 7), over a pool of
// samples that know their place and domain: the current segment's real
// observations, the traces replayed from the dynamic memory and the rest of
// the dynamic memory. Places travel with traces, so a new-domain anchor (a
// winter frame) finds its positive in the remembered trace of the same place
// (a summer frame): that pairing is what teaches domain invariance.
//
// Pure: no torch, no I/O. Descriptors, where given, are unit vectors.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_TRIPLETS_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_TRIPLETS_H_

#include <cstddef>
#include <random>
#include <span>
#include <vector>

#include "services/core/types.h"

namespace fleetmem::robot::gpl {

struct TripletSample {
  core::Place place;
  // Small integer naming the domain (e.g. 0 summer, 1 winter).
  int domain = 0;
};

struct TripletMiningOptions {
  // Positives lie within this distance of the anchor's place (place units;
  // Nordland: 10 per file, so 20 = the +-2 files of a correct match).
  double positive_radius = 20.0;
  // Negatives lie farther than this.
  double negative_radius = 100.0;
  // Draw the positive among those of another domain when there is one.
  bool prefer_other_domain = true;
  // Random negative candidates per anchor; with descriptors, the nearest of
  // them in descriptor space is taken, else the first. Few candidates keep
  // the mining mild: with 16, the head collapsed (every descriptor alike)
  // in the evaluation's measurements (docs/results.md).
  size_t negative_candidates = 4;
};

struct TripletIndex {
  size_t anchor = 0;
  size_t positive = 0;
  size_t negative = 0;
};

// One triplet per anchor (indices into `pool`) that has a positive and a
// negative in the pool; anchors without either are left out. `descriptors`
// is empty or has one entry per pool sample.
std::vector<TripletIndex> MineTriplets(
    std::span<const TripletSample> pool, std::span<const size_t> anchors,
    std::span<const std::vector<float>> descriptors,
    const TripletMiningOptions& options, std::mt19937_64& rng);

// Eq. 7's max over positives and negatives: for each anchor, the positive
// farthest from it in descriptor space and the negative nearest to it. An
// anchor without a positive is its own positive (distance 0); one without a
// negative is left out. `descriptors` has one entry per pool sample.
std::vector<TripletIndex> HardestTriplets(
    std::span<const TripletSample> pool, std::span<const size_t> anchors,
    std::span<const std::vector<float>> descriptors,
    const TripletMiningOptions& options);

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_TRIPLETS_H_
