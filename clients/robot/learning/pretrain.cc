#include "clients/robot/learning/pretrain.h"

#include <chrono>
#include <cmath>

#include "absl/strings/str_format.h"
#include "opencv2/imgproc.hpp"

namespace fleetmem::robot::gpl {

cv::Mat Augment(const cv::Mat& image, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  const double gamma =
      std::exp(std::log(0.5) + u(rng) * (std::log(2.0) - std::log(0.5)));
  const double contrast = 0.6 + 0.8 * u(rng);
  cv::Mat lut(1, 256, CV_8UC1);
  for (int v = 0; v < 256; ++v) {
    const double g = 255.0 * std::pow(v / 255.0, gamma);
    lut.at<uint8_t>(v) =
        cv::saturate_cast<uint8_t>(128.0 + contrast * (g - 128.0));
  }
  cv::Mat out;
  cv::LUT(image, lut, out);
  if (u(rng) < 0.5)
    cv::GaussianBlur(out, out, cv::Size(0, 0), 0.3 + 1.2 * u(rng));
  cv::Mat noise(out.size(), CV_16SC1);
  cv::randn(noise, 0, 12.0 * u(rng));
  cv::Mat widened;
  out.convertTo(widened, CV_16SC1);
  cv::Mat(widened + noise).convertTo(out, CV_8UC1);
  return out;
}

absl::StatusOr<std::unique_ptr<GplModel>> PretrainFleetEncoder(
    std::span<const cv::Mat> images, std::span<const double> positions,
    const PretrainOptions& options) {
  if (images.size() != positions.size() || images.size() < 3) {
    return absl::InvalidArgumentError(
        absl::StrFormat("pre-training needs as many positions as images, at "
                        "least 3 (%d images, %d "
                        "positions)",
                        images.size(), positions.size()));
  }
  // Every anchor's positives and negatives, by position.
  const size_t n = images.size();
  std::vector<std::vector<size_t>> positives(n), negatives(n);
  std::vector<size_t> anchors;
  for (size_t a = 0; a < n; ++a) {
    for (size_t j = 0; j < n; ++j) {
      const double d = std::abs(positions[a] - positions[j]);
      if (j != a && d <= options.positive_radius) positives[a].push_back(j);
      if (d > options.negative_radius) negatives[a].push_back(j);
    }
    if (!positives[a].empty() && !negatives[a].empty()) anchors.push_back(a);
  }
  if (anchors.empty()) {
    return absl::InvalidArgumentError(
        "no frame has both a positive and a negative: the frames span too "
        "little of "
        "the route for the radii");
  }
  absl::StatusOr<std::unique_ptr<GplModel>> model =
      GplModel::Create(options.model, options.version);
  if (!model.ok()) return model.status();
  absl::StatusOr<std::vector<std::vector<float>>> codes =
      (*model)->Encode(images);
  if (!codes.ok()) return codes.status();
  if (absl::Status s = (*model)->InitialisePlaceHead(*codes); !s.ok()) return s;
  std::mt19937_64 rng(options.seed);
  auto pick = [&](const std::vector<size_t>& from) {
    return from[std::uniform_int_distribution<size_t>(0, from.size() - 1)(rng)];
  };
  const auto start = std::chrono::steady_clock::now();
  for (int step = 0; step < options.steps; ++step) {
    ImageTriplets batch;
    for (int i = 0; i < options.batch_size; ++i) {
      const size_t a = pick(anchors);
      batch.anchors.push_back(Augment(images[a], rng));
      batch.positives.push_back(Augment(images[pick(positives[a])], rng));
      batch.negatives.push_back(Augment(images[pick(negatives[a])], rng));
    }
    absl::StatusOr<StepLosses> l = (*model)->TrainJoint(batch);
    if (!l.ok()) return l.status();
    if (options.log && ((step + 1) % 50 == 0 || step + 1 == options.steps)) {
      options.log(absl::StrFormat(
          "[pretrain] step %d/%d: L_loc %.3f L_rec %.3f L_gan(G) %.3f L_gan(D) "
          "%.3f (%.0f s)",
          step + 1, options.steps, l->loc, l->rec, l->gan_g, l->gan_d,
          std::chrono::duration<double>(std::chrono::steady_clock::now() -
                                        start)
              .count()));
    }
  }
  (*model)->FreezeEncoder();
  return model;
}

}  // namespace fleetmem::robot::gpl
