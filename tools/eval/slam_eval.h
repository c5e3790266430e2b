// fleetmem-eval slam: the laser SLAM back end (clients/robot/slam) on a
// CARMEN log with a relations file, three ways: raw odometry, scan-matched
// odometry (no loops), and scan matching with loops from the robot's own
// memory (its keyframe codes searched robot-side, with a position prior).
// Writes per-variant TUM trajectories and occupancy maps, summary.csv and a
// table (docs/slam.md).
#ifndef FLEETMEM_TOOLS_EVAL_SLAM_EVAL_H_
#define FLEETMEM_TOOLS_EVAL_SLAM_EVAL_H_

#include <string>

#include "absl/status/status.h"

namespace fleetmem::eval {

struct SlamEvalOptions {
  std::string log;
  std::string relations;
  std::string out_dir;
  // Scan code for place recognition (clients/robot/sensing/scan_encoder.h).
  std::string encoder = "scanring-r32-d32";
  // Loop candidates per keyframe and the position prior's radius.
  int candidates = 3;
  double prior_radius_m = 8.0;
  // Only the first this many scans of the log (0 = all): the smoke run of
  // the test suite (relations outside them are not scored).
  int max_scans = 0;
};
absl::Status RunSlamEval(const SlamEvalOptions& options);

}  // namespace fleetmem::eval

#endif  // FLEETMEM_TOOLS_EVAL_SLAM_EVAL_H_
