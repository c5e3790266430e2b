// Whole-image HOG (Dalal & Triggs, CVPR 2005) as a holistic place code.
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/sensing/image_encoder.h"
#include "opencv2/imgproc.hpp"
#include "opencv2/objdetect.hpp"

namespace fleetmem::robot {
namespace {

class HogEncoder : public ImageEncoder {
 public:
  explicit HogEncoder(const HogOptions& options)
      : options_(options),
        version_(absl::StrFormat("hog-%dx%d-c%d-s%d-b%d%s-v1", options.width,
                                 options.height, options.cell,
                                 options.block_stride, options.bins,
                                 options.signed_gradient ? "s" : "")),
        hog_(cv::Size(options.width, options.height),
             cv::Size(2 * options.cell, 2 * options.cell),
             cv::Size(options.block_stride, options.block_stride),
             cv::Size(options.cell, options.cell), options.bins,
             /*_derivAperture=*/1, /*_winSigma=*/-1, cv::HOGDescriptor::L2Hys,
             /*_L2HysThreshold=*/0.2,
             /*_gammaCorrection=*/false, cv::HOGDescriptor::DEFAULT_NLEVELS,
             options.signed_gradient) {}

  const std::string& version() const override { return version_; }
  size_t dimension() const override { return hog_.getDescriptorSize(); }

  absl::StatusOr<std::vector<float>> EncodeImage(
      const cv::Mat& grey) const override {
    if (grey.empty() || grey.type() != CV_8UC1) {
      return absl::InvalidArgumentError(
          "HOG encoder needs a non-empty CV_8UC1 image");
    }
    std::vector<float> code;
    try {
      cv::Mat window;
      cv::resize(grey, window, cv::Size(options_.width, options_.height), 0, 0,
                 cv::INTER_AREA);
      hog_.compute(window, code);
    } catch (const cv::Exception& e) {
      return absl::InternalError(absl::StrCat("HOG failed: ", e.what()));
    }
    if (code.size() != dimension()) {
      return absl::InternalError(absl::StrCat(
          "HOG returned ", code.size(), " values, expected ", dimension()));
    }
    return code;
  }

 private:
  HogOptions options_;
  std::string version_;
  cv::HOGDescriptor hog_;
};

}  // namespace

std::unique_ptr<ImageEncoder> NewHogEncoder(const HogOptions& options) {
  const int block = 2 * options.cell;
  if (options.cell <= 0 || options.bins <= 0 || options.block_stride <= 0 ||
      options.block_stride % options.cell != 0 || options.width < block ||
      options.height < block ||
      (options.width - block) % options.block_stride != 0 ||
      (options.height - block) % options.block_stride != 0) {
    return nullptr;
  }
  return std::make_unique<HogEncoder>(options);
}

}  // namespace fleetmem::robot
