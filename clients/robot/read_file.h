// The whole content of a file, for the robot's sources (images, logs), and
// the robot's and evaluations' text outputs.
#ifndef FLEETMEM_CLIENTS_ROBOT_READ_FILE_H_
#define FLEETMEM_CLIENTS_ROBOT_READ_FILE_H_

#include <string>

#include "absl/status/statusor.h"

namespace fleetmem::robot {

// NOT_FOUND naming `path` if it cannot be opened, DATA_LOSS if reading
// fails part-way.
absl::StatusOr<std::string> ReadFile(const std::string& path);

// Replaces `path` with `text`. INTERNAL naming `path` if it cannot be
// written in full (a full disk included).
absl::Status WriteFile(const std::string& path, const std::string& text);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_READ_FILE_H_
