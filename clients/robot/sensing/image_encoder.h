// Classical holistic image codes: one float vector per image, compared by the
// server after L2 normalisation. They implement the robot's Encoder
// (encoder.h) for observations that carry an image.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_IMAGE_ENCODER_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_IMAGE_ENCODER_H_

#include <cstddef>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/sensing/encoder.h"
#include "clients/robot/sensing/rewards.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot {

// An encoder of images. Thread-safe: every method is const.
class ImageEncoder : public Encoder {
 public:
  // Code of an 8-bit single-channel image of any size. INVALID_ARGUMENT for
  // an empty or non-CV_8UC1 image; INTERNAL if OpenCV fails.
  virtual absl::StatusOr<std::vector<float>> EncodeImage(
      const cv::Mat& grey) const = 0;

  // EncodeImage(observation.image); INVALID_ARGUMENT naming the observation
  // if it has no image.
  absl::StatusOr<std::vector<float>> Encode(
      const Observation& observation) const final;
  // The observation with its image shifted and cropped (RandomShiftCrop with
  // the default ShiftCropOptions).
  absl::StatusOr<Observation> Perturb(const Observation& observation,
                                      std::mt19937_64& rng) const final;
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

// Names accepted by NewImageEncoderByName, the default first.
std::vector<std::string> ImageEncoderNames();
// One of ImageEncoderNames(); INVALID_ARGUMENT listing the names otherwise.
absl::StatusOr<std::unique_ptr<ImageEncoder>> NewImageEncoderByName(
    std::string_view name);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_IMAGE_ENCODER_H_
