// The trajectory commands of fleetmem-eval: `trajectory` (ATE, RPE, KITTI
// errors of an estimate against a reference), `relations` (the Freiburg
// metric of a 2-D SLAM estimate) and `continual` (CL-SLAM's AQ/RQ from a
// table of deployments). Each prints a table, or JSON with `json`.
#ifndef FLEETMEM_TOOLS_EVAL_TRAJECTORY_EVAL_H_
#define FLEETMEM_TOOLS_EVAL_TRAJECTORY_EVAL_H_

#include <string>

#include "absl/status/status.h"

namespace fleetmem::eval {

struct TrajectoryEvalOptions {
  std::string reference;
  std::string estimate;
  // "kitti", "tum" or "" (detected from each file).
  std::string format;
  // "se3", "sim3" or "none".
  std::string align = "se3";
  // > 0: RPE pairs by path length in metres; else by rpe_delta_frames.
  double rpe_delta_m = 0.0;
  int rpe_delta_frames = 1;
  bool pairs_from_reference = false;
  // Largest time difference of associated TUM poses (seconds).
  double max_time_diff_s = 0.01;
  bool json = false;
};
absl::Status RunTrajectoryEval(const TrajectoryEvalOptions& options);

struct RelationsEvalOptions {
  std::string estimate;
  std::string relations;
  // Largest difference between a relation's scan time and the estimate's.
  double max_time_diff_s = 0.001;
  bool json = false;
};
absl::Status RunRelationsEval(const RelationsEvalOptions& options);

absl::Status RunContinualScores(const std::string& table, bool json);

}  // namespace fleetmem::eval

#endif  // FLEETMEM_TOOLS_EVAL_TRAJECTORY_EVAL_H_
