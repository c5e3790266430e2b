// fleetmem-eval continual-vo: CL-SLAM's continual visual odometry on the two
// real KITTI clips (docs/continual-vo.md).
//
// For each order (clip X pre-trains, clip Y is the other; the full run does
// both orders, --quick only clip1 first):
//   pre-train on X (stereo + monocular, encoders then frozen);
//   per method (fixed, expert_only, generalizer_only, cl_slam):
//     pre>X>Y     deploy on Y              (adaptation: AQ)
//     pre>X>Y>X   then return to X         (retention: RQ against ...)
//     pre>X>X     deploy on X right after pre-training
//   the classical baseline on each clip.
// "pre" names the random initialisation and X the pre-training, so that
// CL-SLAM's AQ (Eq. 4) and RQ (Eq. 6) apply as fleetmem-eval continual
// computes them. Per deployment: ATE (SE(3) and Sim(3) alignment), RPE per
// frame and per 10 m, and t_err/r_err on 10-40 m segments (the clips are
// 52-60 m: KITTI's 100-800 m segments do not fit). Writes summary.csv,
// continual.csv, trajectories (KITTI and TUM), weights per deployment and
// one plot per method (PNG).
#ifndef FLEETMEM_TOOLS_EVAL_CONTINUAL_VO_EVAL_H_
#define FLEETMEM_TOOLS_EVAL_CONTINUAL_VO_EVAL_H_

#include <string>

#include "absl/status/status.h"

namespace fleetmem::eval {

struct ContinualVoEvalOptions {
  // Holds kitti/clip1 and kitti/clip2 (../shared/data).
  std::string data_root;
  std::string out_dir;
  // One order, fewer pre-training steps (under 10 minutes on 2 cores).
  bool quick = false;
  // Overrides (0: the mode's default).
  int pretrain_steps = 0;
  int update_steps = 5;
  int threads = 2;
  uint64_t seed = 1;
  // Only the first this many frames of each clip (0 = all): the smoke run of
  // the test suite, which proves the code paths and outputs, not the
  // figures. At least 3.
  int frames = 0;
};
absl::Status RunContinualVoEval(const ContinualVoEvalOptions& options);

}  // namespace fleetmem::eval

#endif  // FLEETMEM_TOOLS_EVAL_CONTINUAL_VO_EVAL_H_
