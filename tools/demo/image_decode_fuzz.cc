// libFuzzer harness: the demo's image loading (DecodeGrey, what
// LoadNordlandGrey runs on a file's bytes) and the default encoder on what
// it decodes. OpenCV itself is Debian's uninstrumented build: the fuzzer
// guides itself by this project's code and catches crashes anywhere.
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string_view>

#include "tools/demo/image_encoder.h"
#include "tools/demo/nordland.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace demo = fleetmem::demo;
  absl::StatusOr<cv::Mat> grey = demo::DecodeGrey(
      std::string_view(reinterpret_cast<const char*>(data), size), "input");
  if (!grey.ok()) return 0;
  static const std::unique_ptr<demo::ImageEncoder> encoder =
      std::move(*demo::NewEncoderByName(demo::EncoderNames().front()));
  encoder->Encode(*grey).IgnoreError();
  return 0;
}
