// Robot-side rewards of memory traces (BioSLAM Eqs. 11-13; memory.md
// "Rewards"), computed honestly from the robot's own observations:
//
// - Internal R_in(q) = 1 - cos(E(q), E(A(q))), with A a small random shift
//   and crop of the forward camera image: how much the code of a place moves
//   under a perturbation the place should be invariant to.
// - External R_ex(q) = max(0, d(q, pos) - d(q, neg) + margin), the triplet
//   loss of Eq. 7 on the robot's own stretch: pos is the hardest (farthest in
//   code) frame within `positive_radius` along the route, i.e. an adjacent
//   frame; neg is the hardest (nearest in code) frame farther than
//   `negative_radius`. d is the server's code distance (Euclidean between
//   L2-normalised codes, 0..2).
//
// R = R_ex + R_in (Eq. 13). Both are high for the observations the encoder
// handles worst, which are the ones worth keeping and replaying.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_REWARDS_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_REWARDS_H_

#include <random>
#include <span>
#include <vector>

#include "absl/status/statusor.h"
#include "opencv2/core.hpp"
#include "services/core/types.h"

namespace fleetmem::robot {

// The perturbation A of the internal reward.
struct ShiftCropOptions {
  // The crop keeps all but 2 * max_shift_x columns and 2 * max_shift_y rows,
  // at a uniformly random offset, and is resized back to the image size.
  int max_shift_x = 4;
  int max_shift_y = 2;
};

// A(image). INVALID_ARGUMENT if the image is empty or smaller than the crop
// margins; INTERNAL if OpenCV fails.
absl::StatusOr<cv::Mat> RandomShiftCrop(const cv::Mat& image,
                                        const ShiftCropOptions& options,
                                        std::mt19937_64& rng);

// R_in = 1 - cos(code, perturbed_code), in [0, 2].
float InternalReward(std::span<const float> code,
                     std::span<const float> perturbed_code);

struct TripletOptions {
  // alpha of Eq. 7, in code-distance units.
  double margin = 0.1;
  // Positives: other frames within this distance (place units; Nordland
  // has 10 per file along the route, so 10 = the adjacent frames).
  double positive_radius = 10.0;
  // Negatives: frames farther than this.
  double negative_radius = 100.0;
};

// R_ex of every observation of a segment: codes[i] observed at places[i]
// (distances between places by PlaceDistance). A frame without positives
// uses d(q, pos) = 0; one without negatives gets 0. Sizes of `codes` and
// `places` must match (else an empty result).
std::vector<float> ExternalRewards(std::span<const std::vector<float>> codes,
                                   std::span<const core::Place> places,
                                   const TripletOptions& options);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_REWARDS_H_
