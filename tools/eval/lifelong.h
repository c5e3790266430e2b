// `fleetmem-eval lifelong`: BioSLAM's lifelong place-recognition protocol
// on a Nordland-layout data root, every method in one run with the same
// seeds (docs/results.md, "Lifelong learning").
//
// Protocol v2 (lifelong_protocol.h): the route (frames present in both
// seasons, in file order) is split into 3 areas; within each area every 4th
// place is held out and never trained on, in either season. The map is the
// summer frame of every place, held-out places included; the queries are
// the winter frames of the held-out places; correct within +-2 files.
// Domains: summer areas 1-3, then winter areas 1-3, each frame arriving
// once, in route order, in segments; learning only from training places.
// After each domain: Recall@1..6 and WR of each area's queries; AE, RA and
// WR final as lifelong_protocol.h's Summarise; the chance level.
//
// Methods (LifelongMethodNames): classical (HOG cosine), classical_seq (HOG
// with sequence matching), and the robot's two learners, each run through
// the robot's own segment step (clients/robot/runtime/segment_step.h): the
// metric head on the HOG fleet code (metric_robot.h: joint, finetune, bioslam,
// uniform_replay with bioslam's trace budget, no_rex, no_rin,
// no_clustering, no_decay, fleet_shared) and the GPL head on the frozen GPL
// encoder (gpl_robot.h: gpl_pretrained, gpl_joint, gpl_finetune,
// gpl_bioslam, gpl_bioslam_decoded). Every method that remembers through
// the fleet runs a real fleetmem-server child.
#ifndef FLEETMEM_TOOLS_EVAL_LIFELONG_H_
#define FLEETMEM_TOOLS_EVAL_LIFELONG_H_

#include <cstdint>
#include <string>
#include <vector>

#include "absl/status/status.h"

namespace fleetmem::eval {

struct LifelongOptions {
  // Folder with nordland/{summer,winter}/images-NNNNN.png.
  std::string data_root;
  // Output folder (created): summary.csv, summary.md, curves.csv,
  // curves.png, memory.csv, fleet.csv, encoder-seedN.pt (GPL methods),
  // servers/, logs.
  std::string out_dir;
  // The fleetmem-server binary (default: beside this program).
  std::string server_binary;
  // Methods to run (empty = all), by name.
  std::vector<std::string> methods;
  // Quick settings (under 10 minutes on 2 cores) instead of the full ones.
  bool quick = false;
  // Seeds options.seed, options.seed + 1, ...: `seeds` runs of every
  // method (0 = the settings' 1 quick, 3 full); the report gives mean and
  // standard deviation.
  uint64_t seed = 1;
  int seeds = 0;
  int threads = 2;
  // Overrides of the settings (0 or negative = the quick/full default).
  int pretrain_steps = 0;
  int end_to_end_steps = 0;
  int steps_per_segment = 0;
  int negative_candidates = 0;
  double head_learning_rate = 0;
  double gan_weight = -1;
  // D of the GPL codes (memory.md's 256 by default).
  int code_dimension = 256;
  // Only the first this many places of the route (0 = all): the smoke runs
  // of the test suite (a few dozen places prove the code paths and outputs,
  // not the figures). At least 24.
  int max_places = 0;
  // Overrides of the metric head's update rate and partners per sample, and
  // of the fleet memory's spatial scale (0 = their defaults).
  double metric_update_rate = 0;
  int metric_partners = 0;
  double spatial_scale = 0;
  // Places skipped at the start of the route (the rest is the route): a
  // stretch of the data no setting was tuned on.
  int skip_places = 0;
  // *_seq_robot: map places each frame takes into the robot's sequence
  // search (fleetmem-robot's --sequence-candidates).
  int sequence_candidates = 20;
};

absl::Status RunLifelong(const LifelongOptions& options);

// Every method name, in report order.
std::vector<std::string> LifelongMethodNames();

}  // namespace fleetmem::eval

#endif  // FLEETMEM_TOOLS_EVAL_LIFELONG_H_
