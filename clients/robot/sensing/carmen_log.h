// CARMEN robot logs (the Radish / Freiburg 2-D laser SLAM datasets): text
// lines, `FLASER n r_1 ... r_n x y theta odom_x odom_y odom_theta
// ipc_timestamp ipc_hostname logger_timestamp` for a front laser scan of n
// beams over 180 degrees, taken at pose (x, y, theta). Other messages (ODOM,
// PARAM, comments) are skipped.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_CARMEN_LOG_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_CARMEN_LOG_H_

#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/sensing/observation.h"

namespace fleetmem::robot {

// The FLASER records of a log's text, in order, as observations: place =
// (x, y, 0, theta), timestamp = ipc_timestamp, name = "NAME:LINE".
// INVALID_ARGUMENT naming `name` and the line for a FLASER line that is cut
// short or holds a value that is not a number (ranges must be finite and
// >= 0, beams 1..4096); NOT_FOUND if the log holds no FLASER record.
absl::StatusOr<std::vector<Observation>> ParseCarmenLog(
    std::string_view text, const std::string& name);

// The whole text of `path`, decompressed through libbz2 if the name ends in
// ".bz2". NOT_FOUND if it cannot be opened; DATA_LOSS naming the file for a
// corrupt or truncated bzip2 stream.
absl::StatusOr<std::string> ReadMaybeBzip2(const std::string& path);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_CARMEN_LOG_H_
