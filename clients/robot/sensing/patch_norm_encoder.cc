// SeqSLAM-style patch-normalised thumbnails (Milford & Wyeth, ICRA 2012).
#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/sensing/image_encoder.h"
#include "opencv2/imgproc.hpp"

namespace fleetmem::robot {
namespace {

// Blocks whose standard deviation is below this (grey levels) are flat.
constexpr double kFlatStdDev = 1e-3;

class PatchNormEncoder : public ImageEncoder {
 public:
  explicit PatchNormEncoder(const PatchNormOptions& options)
      : options_(options),
        version_(absl::StrFormat("patchnorm-%dx%d-p%d-v1", options.width,
                                 options.height, options.patch)) {}

  const std::string& version() const override { return version_; }
  size_t dimension() const override {
    return static_cast<size_t>(options_.width) * options_.height;
  }

  absl::StatusOr<std::vector<float>> EncodeImage(
      const cv::Mat& grey) const override {
    if (grey.empty() || grey.type() != CV_8UC1) {
      return absl::InvalidArgumentError(
          "patch-norm encoder needs a non-empty CV_8UC1 image");
    }
    cv::Mat small;
    try {
      cv::resize(grey, small, cv::Size(options_.width, options_.height), 0, 0,
                 cv::INTER_AREA);
      small.convertTo(small, CV_32F);
    } catch (const cv::Exception& e) {
      return absl::InternalError(absl::StrCat("resize failed: ", e.what()));
    }
    const int p = options_.patch;
    for (int y = 0; y < options_.height; y += p) {
      for (int x = 0; x < options_.width; x += p) {
        cv::Mat block = small(cv::Rect(x, y, p, p));
        cv::Scalar mean, stddev;
        cv::meanStdDev(block, mean, stddev);
        if (stddev[0] < kFlatStdDev) {
          block.setTo(0.0f);
        } else {
          block.convertTo(block, CV_32F, 1.0 / stddev[0], -mean[0] / stddev[0]);
        }
      }
    }
    return std::vector<float>(small.begin<float>(), small.end<float>());
  }

 private:
  PatchNormOptions options_;
  std::string version_;
};

}  // namespace

std::unique_ptr<ImageEncoder> NewPatchNormEncoder(
    const PatchNormOptions& options) {
  if (options.width <= 0 || options.height <= 0 || options.patch <= 0 ||
      options.width % options.patch != 0 ||
      options.height % options.patch != 0) {
    return nullptr;
  }
  return std::make_unique<PatchNormEncoder>(options);
}

}  // namespace fleetmem::robot
