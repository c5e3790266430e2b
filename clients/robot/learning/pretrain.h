// Pre-training of a fleet's shared encoder (learning.md, fleet decision: the
// encoder is trained once on an initial domain, then frozen): L_joint
// (Eq. 10) on E, F, G and D over one domain's frames, triplets by position
// along the route, each image photometrically augmented so that the encoder
// learns that light, contrast, blur and sensor noise are not place.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_PRETRAIN_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_PRETRAIN_H_

#include <functional>
#include <memory>
#include <random>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/learning/gpl_model.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot::gpl {

struct PretrainOptions {
  GplOptions model;
  // Encoder version given to the model (travels with every code).
  std::string version = "gpl-64x32-d256-v1";
  int steps = 1000;
  // Triplets per step.
  int batch_size = 16;
  // Positions within this distance are positives, beyond the second
  // negatives (place units).
  double positive_radius = 20.0;
  double negative_radius = 100.0;
  uint64_t seed = 1;
  // Progress lines (every 50 steps); may be empty.
  std::function<void(std::string_view)> log;
};

// A random photometric change: gamma in [0.5, 2], contrast in [0.6, 1.4], a
// Gaussian blur (sigma up to 1.5 px) half of the time, noise of up to 12
// grey levels. `image` is 8-bit grey.
cv::Mat Augment(const cv::Mat& image, std::mt19937_64& rng);

// A new model trained on `images` observed at `positions` (one coordinate
// along the route), with the place head initialised from the data and the
// encoder frozen at the end. INVALID_ARGUMENT if the sizes differ or no
// triplet can be formed.
absl::StatusOr<std::unique_ptr<GplModel>> PretrainFleetEncoder(
    std::span<const cv::Mat> images, std::span<const double> positions,
    const PretrainOptions& options);

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_PRETRAIN_H_
