#include "clients/robot/sensing/encoder_factory.h"

#include <algorithm>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "clients/robot/sensing/image_encoder.h"
#include "clients/robot/sensing/scan_encoder.h"

namespace fleetmem::robot {

std::vector<std::string> EncoderNames() {
  std::vector<std::string> names = ImageEncoderNames();
  for (std::string& name : ScanEncoderNames()) names.push_back(name);
  return names;
}

absl::StatusOr<std::unique_ptr<Encoder>> NewEncoderByName(
    std::string_view name) {
  const std::vector<std::string> images = ImageEncoderNames();
  if (std::find(images.begin(), images.end(), name) != images.end()) {
    absl::StatusOr<std::unique_ptr<ImageEncoder>> encoder =
        NewImageEncoderByName(name);
    if (!encoder.ok()) return encoder.status();
    return std::unique_ptr<Encoder>(*std::move(encoder));
  }
  const std::vector<std::string> scans = ScanEncoderNames();
  if (std::find(scans.begin(), scans.end(), name) != scans.end()) {
    return NewScanEncoderByName(name);
  }
  return absl::InvalidArgumentError(
      absl::StrCat("unknown encoder \"", std::string(name),
                   "\"; known: ", absl::StrJoin(EncoderNames(), ", ")));
}

}  // namespace fleetmem::robot
