#include "clients/robot/sensing/image_encoder.h"

#include <variant>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace fleetmem::robot {
namespace {

struct NamedEncoder {
  const char* name;
  std::variant<HogOptions, PatchNormOptions> options;
};

// The variants compared by fleetmem-encoder-eval (see tools/demo/README.md
// for their measured recall); the first is the default.
constexpr NamedEncoder kEncoders[] = {
    {"hog-64x32-c8-s8-b6", HogOptions{.cell = 8, .block_stride = 8, .bins = 6}},
    {"patchnorm-32x16-p8", PatchNormOptions{.patch = 8}},
    {"patchnorm-32x16-p4", PatchNormOptions{.patch = 4}},
    {"patchnorm-32x16-p16", PatchNormOptions{.patch = 16}},
    {"patchnorm-16x8-p4",
     PatchNormOptions{.width = 16, .height = 8, .patch = 4}},
    {"hog-64x32-c8-s16", HogOptions{.cell = 8, .block_stride = 16}},
    {"hog-64x32-c8-s8", HogOptions{.cell = 8, .block_stride = 8}},
    {"hog-64x32-c8-s16-b12s",
     HogOptions{
         .cell = 8, .block_stride = 16, .bins = 12, .signed_gradient = true}},
    {"hog-64x32-c16-s16", HogOptions{.cell = 16, .block_stride = 16}},
    {"hog-32x16-c4-s4",
     HogOptions{.width = 32, .height = 16, .cell = 4, .block_stride = 4}},
};

std::unique_ptr<ImageEncoder> Make(const NamedEncoder& entry) {
  if (const auto* hog = std::get_if<HogOptions>(&entry.options)) {
    return NewHogEncoder(*hog);
  }
  return NewPatchNormEncoder(std::get<PatchNormOptions>(entry.options));
}

}  // namespace

absl::StatusOr<std::vector<float>> ImageEncoder::Encode(
    const Observation& observation) const {
  if (observation.image.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "image encoder ", version(), " got ", observation.name,
        ", which holds no image (a laser scan needs a scan encoder)"));
  }
  return EncodeImage(observation.image);
}

absl::StatusOr<Observation> ImageEncoder::Perturb(
    const Observation& observation, std::mt19937_64& rng) const {
  absl::StatusOr<cv::Mat> moved =
      RandomShiftCrop(observation.image, ShiftCropOptions{}, rng);
  if (!moved.ok()) return moved.status();
  Observation perturbed = observation;
  perturbed.image = *std::move(moved);
  return perturbed;
}

std::vector<std::string> ImageEncoderNames() {
  std::vector<std::string> names;
  for (const NamedEncoder& entry : kEncoders) names.push_back(entry.name);
  return names;
}

absl::StatusOr<std::unique_ptr<ImageEncoder>> NewImageEncoderByName(
    std::string_view name) {
  for (const NamedEncoder& entry : kEncoders) {
    if (name == entry.name) return Make(entry);
  }
  return absl::InvalidArgumentError(
      absl::StrCat("unknown encoder \"", std::string(name),
                   "\"; known: ", absl::StrJoin(ImageEncoderNames(), ", ")));
}

}  // namespace fleetmem::robot
