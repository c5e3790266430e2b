// The robot's encoders by name (fleetmem-robot --encoder, the evaluations):
// the image codes (image_encoder.h), then the scan codes (scan_encoder.h).
// Apart from the Encoder interface (encoder.h), which the learned model
// implements too, so that an encoder need not link every other.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_ENCODER_FACTORY_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_ENCODER_FACTORY_H_

#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/sensing/encoder.h"

namespace fleetmem::robot {

// Names accepted by NewEncoderByName: the image codes, then the scan codes.
std::vector<std::string> EncoderNames();
// One of EncoderNames(); INVALID_ARGUMENT listing the names otherwise.
absl::StatusOr<std::unique_ptr<Encoder>> NewEncoderByName(
    std::string_view name);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_ENCODER_FACTORY_H_
