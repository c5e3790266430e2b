#include "clients/robot/sensing/rewards.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "clients/robot/sensing/code_search.h"
#include "opencv2/imgproc.hpp"

namespace fleetmem::robot {

absl::StatusOr<cv::Mat> RandomShiftCrop(const cv::Mat& image,
                                        const ShiftCropOptions& options,
                                        std::mt19937_64& rng) {
  const int crop_w = image.cols - 2 * options.max_shift_x;
  const int crop_h = image.rows - 2 * options.max_shift_y;
  if (image.empty() || options.max_shift_x < 0 || options.max_shift_y < 0 ||
      crop_w <= 0 || crop_h <= 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cannot crop a ", image.cols, "x", image.rows, " image by ",
        options.max_shift_x, "/", options.max_shift_y, " pixels per side"));
  }
  std::uniform_int_distribution<int> dx(0, 2 * options.max_shift_x);
  std::uniform_int_distribution<int> dy(0, 2 * options.max_shift_y);
  const cv::Rect window(dx(rng), dy(rng), crop_w, crop_h);
  cv::Mat out;
  try {
    cv::resize(image(window), out, image.size(), 0, 0, cv::INTER_LINEAR);
  } catch (const cv::Exception& e) {
    return absl::InternalError(absl::StrCat("shift-crop failed: ", e.what()));
  }
  return out;
}

float InternalReward(std::span<const float> code,
                     std::span<const float> perturbed_code) {
  return 1.0f - CosineSimilarity(code, perturbed_code);
}

std::vector<float> ExternalRewards(std::span<const std::vector<float>> codes,
                                   std::span<const core::Place> places,
                                   const TripletOptions& options) {
  const size_t n = codes.size();
  if (places.size() != n) return {};
  // All pairwise distances once: a stretch is a few hundred frames.
  std::vector<float> distance(n * n, 0.0f);
  for (size_t i = 0; i < n; ++i) {
    for (size_t j = i + 1; j < n; ++j) {
      distance[i * n + j] = distance[j * n + i] =
          CodeDistance(codes[i], codes[j]);
    }
  }
  std::vector<float> rewards(n, 0.0f);
  for (size_t i = 0; i < n; ++i) {
    float hardest_positive = 0.0f;
    float hardest_negative = std::numeric_limits<float>::infinity();
    for (size_t j = 0; j < n; ++j) {
      const double along = PlaceDistance(places[j], places[i]);
      if (j != i && along <= options.positive_radius) {
        hardest_positive = std::max(hardest_positive, distance[i * n + j]);
      } else if (along > options.negative_radius) {
        hardest_negative = std::min(hardest_negative, distance[i * n + j]);
      }
    }
    if (std::isinf(hardest_negative)) continue;
    rewards[i] = static_cast<float>(
        std::max(0.0, hardest_positive - hardest_negative + options.margin));
  }
  return rewards;
}

}  // namespace fleetmem::robot
