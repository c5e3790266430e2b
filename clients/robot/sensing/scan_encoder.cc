#include "clients/robot/sensing/scan_encoder.h"

#include <algorithm>
#include <cmath>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"

namespace fleetmem::robot {
namespace {

bool IsReturn(float range, float max_range) {
  return std::isfinite(range) && range > 0.0f && range < max_range;
}

class ScanRingEncoder : public Encoder {
 public:
  explicit ScanRingEncoder(const ScanRingOptions& options)
      : options_(options),
        version_(absl::StrFormat("scanring-r%d-d%d-m%g-v1", options.range_bins,
                                 options.distance_bins,
                                 options.histogram_range_m)) {}

  const std::string& version() const override { return version_; }
  size_t dimension() const override {
    return static_cast<size_t>(options_.range_bins + 1 +
                               options_.distance_bins);
  }

  absl::StatusOr<std::vector<float>> Encode(
      const Observation& observation) const override {
    const LaserScan& scan = observation.scan;
    if (scan.ranges.empty()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "scan encoder ", version_, " got ", observation.name,
          ", which holds no laser scan (an image needs an image encoder)"));
    }
    std::vector<float> code(dimension(), 0.0f);
    const double ring = options_.histogram_range_m / options_.range_bins;
    const double bin = options_.histogram_range_m / options_.distance_bins;
    const size_t beams = scan.ranges.size();
    const double step =
        beams > 1 ? scan.field_of_view / static_cast<double>(beams - 1) : 0.0;
    std::vector<std::pair<double, double>> points;
    points.reserve(beams);
    for (size_t i = 0; i < beams; ++i) {
      const float range = scan.ranges[i];
      if (!IsReturn(range, scan.max_range)) {
        code[options_.range_bins] += 1.0f;
        continue;
      }
      const int r =
          std::min(options_.range_bins - 1, static_cast<int>(range / ring));
      code[r] += 1.0f;
      const double bearing = -scan.field_of_view / 2.0 + step * i;
      points.emplace_back(range * std::cos(bearing), range * std::sin(bearing));
    }
    for (int r = 0; r <= options_.range_bins; ++r) code[r] /= beams;
    const size_t offset = options_.range_bins + 1;
    double pairs = 0.0;
    for (size_t i = 0; i < points.size(); ++i) {
      for (size_t j = i + 1; j < points.size(); ++j) {
        const double d = std::hypot(points[i].first - points[j].first,
                                    points[i].second - points[j].second);
        const int b =
            std::min(options_.distance_bins - 1, static_cast<int>(d / bin));
        code[offset + b] += 1.0f;
        pairs += 1.0;
      }
    }
    if (pairs > 0.0) {
      for (size_t b = offset; b < code.size(); ++b) code[b] /= pairs;
    }
    return code;
  }

  absl::StatusOr<Observation> Perturb(const Observation& observation,
                                      std::mt19937_64& rng) const override {
    if (observation.scan.ranges.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat(observation.name, " holds no laser scan to rotate"));
    }
    std::uniform_int_distribution<int> shift(-options_.max_rotation_beams,
                                             options_.max_rotation_beams);
    const int k = shift(rng);
    Observation rotated = observation;
    const int n = static_cast<int>(observation.scan.ranges.size());
    for (int i = 0; i < n; ++i) {
      const int from = i - k;
      rotated.scan.ranges[i] =
          from >= 0 && from < n ? observation.scan.ranges[from] : 0.0f;
    }
    return rotated;
  }

 private:
  ScanRingOptions options_;
  std::string version_;
};

struct NamedScanEncoder {
  const char* name;
  ScanRingOptions options;
};

constexpr NamedScanEncoder kScanEncoders[] = {
    {"scanring-r32-d32", ScanRingOptions{}},
    {"scanring-r16-d16",
     ScanRingOptions{.range_bins = 16, .distance_bins = 16}},
};

}  // namespace

std::unique_ptr<Encoder> NewScanRingEncoder(const ScanRingOptions& options) {
  if (options.range_bins < 1 || options.distance_bins < 1 ||
      !(options.histogram_range_m > 0.0) || options.max_rotation_beams < 0) {
    return nullptr;
  }
  return std::make_unique<ScanRingEncoder>(options);
}

std::vector<std::string> ScanEncoderNames() {
  std::vector<std::string> names;
  for (const NamedScanEncoder& entry : kScanEncoders) {
    names.push_back(entry.name);
  }
  return names;
}

absl::StatusOr<std::unique_ptr<Encoder>> NewScanEncoderByName(
    std::string_view name) {
  for (const NamedScanEncoder& entry : kScanEncoders) {
    if (name == entry.name) return NewScanRingEncoder(entry.options);
  }
  return absl::InvalidArgumentError(
      absl::StrCat("unknown scan encoder \"", std::string(name),
                   "\"; known: ", absl::StrJoin(ScanEncoderNames(), ", ")));
}

}  // namespace fleetmem::robot
