// libFuzzer harness: the robot's image loading (DecodeGrey, what
// LoadNordlandGrey runs on a file's bytes) and the default encoder on what
// it decodes. OpenCV itself is Debian's uninstrumented build: the fuzzer
// guides itself by this project's code and catches crashes anywhere.
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string_view>

#include "clients/robot/sensing/image_encoder.h"
#include "clients/robot/sensing/nordland.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace robot = fleetmem::robot;
  absl::StatusOr<cv::Mat> grey = robot::DecodeGrey(
      std::string_view(reinterpret_cast<const char*>(data), size), "input");
  if (!grey.ok()) return 0;
  static const std::unique_ptr<robot::ImageEncoder> encoder = std::move(
      *robot::NewImageEncoderByName(robot::ImageEncoderNames().front()));
  encoder->EncodeImage(*grey).IgnoreError();
  return 0;
}
