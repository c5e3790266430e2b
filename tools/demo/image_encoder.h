// Classical holistic image codes, the robot-side encoder E of the demo: one
// float vector per image, compared by the server after L2 normalisation.
// Codes of different encoders (or options) are not comparable; each encoder
// names itself by a version string that travels with every trace.
#ifndef FLEETMEM_TOOLS_DEMO_IMAGE_ENCODER_H_
#define FLEETMEM_TOOLS_DEMO_IMAGE_ENCODER_H_

#include <cstddef>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "opencv2/core.hpp"

namespace fleetmem::demo {

// Thread-safe: Encode is const and keeps no state between calls.
class ImageEncoder {
 public:
  virtual ~ImageEncoder() = default;

  // Version carried by every trace, e.g. "patchnorm-32x16-p8-v1".
  virtual const std::string& version() const = 0;
  // Size of every code Encode returns.
  virtual size_t dimension() const = 0;
  // Code of an 8-bit single-channel image of any size. INVALID_ARGUMENT for
  // an empty or non-CV_8UC1 image; INTERNAL if OpenCV fails.
  virtual absl::StatusOr<std::vector<float>> Encode(
      const cv::Mat& grey) const = 0;
};

// SeqSLAM-style code: resize to width x height (area averaging), then
// normalise every non-overlapping patch x patch block to zero mean and unit
// variance (a flat block, e.g. of a black frame, becomes zeros), flatten.
struct PatchNormOptions {
  // Size of the resized image; dimension = width * height.
  int width = 32;
  int height = 16;
  // Side of the normalised blocks; must divide width and height.
  int patch = 8;
};
// Returns nullptr if the options are out of range.
std::unique_ptr<ImageEncoder> NewPatchNormEncoder(
    const PatchNormOptions& options);

// Histogram of oriented gradients (cv::HOGDescriptor) over the whole image,
// resized to width x height first.
struct HogOptions {
  // Window = resized image; multiples of cell.
  int width = 64;
  int height = 32;
  // Cell side in pixels; blocks are 2x2 cells.
  int cell = 8;
  // Block stride in pixels (a multiple of cell).
  int block_stride = 16;
  // Orientation bins per cell.
  int bins = 9;
  // Orientations over 360 degrees instead of 180.
  bool signed_gradient = false;
};
// Returns nullptr if the options are out of range.
std::unique_ptr<ImageEncoder> NewHogEncoder(const HogOptions& options);

// Names accepted by NewEncoderByName, the demo's default first.
std::vector<std::string> EncoderNames();
// One of EncoderNames(); INVALID_ARGUMENT listing the names otherwise.
absl::StatusOr<std::unique_ptr<ImageEncoder>> NewEncoderByName(
    std::string_view name);

}  // namespace fleetmem::demo

#endif  // FLEETMEM_TOOLS_DEMO_IMAGE_ENCODER_H_
