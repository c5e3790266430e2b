// The whole content of a file, for the robot's sources (images, logs).
#ifndef FLEETMEM_CLIENTS_ROBOT_READ_FILE_H_
#define FLEETMEM_CLIENTS_ROBOT_READ_FILE_H_

#include <string>

#include "absl/status/statusor.h"

namespace fleetmem::robot {

// NOT_FOUND naming `path` if it cannot be opened, DATA_LOSS if reading
// fails part-way.
absl::StatusOr<std::string> ReadFile(const std::string& path);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_READ_FILE_H_
