// `fleetmem-eval lifelong`: BioSLAM's lifelong place-recognition protocol
// on a Nordland-layout data root, every method in one run with the same
// seeds (docs/results.md, "Lifelong learning").
//
// Protocol (fixed): the route (frames present in both seasons, in file
// order) is split into 3 areas; domains are summer areas 1-3 then winter
// areas 1-3, each observation arriving once, in route order, in segments.
// Every 4th frame of the route is a held-out query, never trained on. The
// database is the summer training frames of the whole route (the fleet's
// map); a query is correct when a retrieved frame is within +-2 files.
// After each domain: Recall@1..6 and WR of every domain's queries; AE = WR
// on the domain just learned, RA = mean WR on the earlier domains; WR on the
// domains not yet learned is the generalisation.
//
// Methods: classical (HOG, no learning), gpl_pretrained (the fleet encoder
// and head after pre-training, no lifelong learning), finetune,
// uniform_replay, bioslam, no_rex, no_rin, no_clustering, no_decay,
// bioslam_decoded (replay through the decoder) and fleet_shared. Every
// method that remembers runs through a real fleetmem-server child.
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
  // Output folder (created): summary.csv, curves.csv, curves.png, fleet.csv,
  // encoder.pt, servers/, logs.
  std::string out_dir;
  // The fleetmem-server binary (default: beside this program).
  std::string server_binary;
  // Methods to run (empty = all), by name.
  std::vector<std::string> methods;
  // Quick settings (under 10 minutes on 2 cores) instead of the full ones.
  bool quick = false;
  uint64_t seed = 1;
  int threads = 2;
  // Overrides of the settings (0 or negative = the quick/full default).
  int pretrain_steps = 0;
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
};

absl::Status RunLifelong(const LifelongOptions& options);

// Every method name, in report order.
std::vector<std::string> LifelongMethodNames();

}  // namespace fleetmem::eval

#endif  // FLEETMEM_TOOLS_EVAL_LIFELONG_H_
