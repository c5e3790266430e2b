// The robot's encoder E: one float code per observation, versioned. Codes of
// different encoders (or of one encoder with other options) are not
// comparable, so every encoder names itself by a version string that travels
// with every trace it makes (a fleet holds one version at a time). The
// classical image codes (image_encoder.h), the rotation-invariant scan code
// (scan_encoder.h) and the learned model of the next step implement it;
// encoder_factory.h makes one by name.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_ENCODER_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_ENCODER_H_

#include <cstddef>
#include <memory>
#include <random>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/sensing/observation.h"

namespace fleetmem::robot {

// Thread-safe: every method is const and keeps no state between calls.
class Encoder {
 public:
  virtual ~Encoder() = default;

  // Version carried by every trace, e.g. "hog-64x32-c8-s8-b6-v1".
  virtual const std::string& version() const = 0;
  // Size of every code Encode returns.
  virtual size_t dimension() const = 0;
  // Code of `observation`. INVALID_ARGUMENT if the observation is not of the
  // encoder's kind (an image encoder given a scan) or malformed.
  virtual absl::StatusOr<std::vector<float>> Encode(
      const Observation& observation) const = 0;
  // A(q) of the internal reward (Eq. 12): a random change of the observation
  // that its place code should be invariant to (a small shift and crop of a
  // forward camera image, a rotation of a scan about the vertical axis).
  virtual absl::StatusOr<Observation> Perturb(const Observation& observation,
                                              std::mt19937_64& rng) const = 0;
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_ENCODER_H_
