// fleetmem-eval: evaluations of the robot side on recorded data.
//
//   fleetmem-eval lifelong --data-root DIR --out DIR [--quick]
//       BioSLAM's lifelong place-recognition protocol, every method
//       (tools/eval/lifelong.h, docs/results.md).
//
// Exit codes: 0 done, 1 the run failed (message on stderr), 2 bad usage.
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_join.h"
#include "tools/eval/lifelong.h"

namespace {

std::string BesideThisProgram(const std::string& name) {
  std::error_code ec;
  const std::filesystem::path self = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (ec) return name;
  return (self.parent_path() / name).string();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"fleetmem-eval: evaluations of fleetmem's robot side on recorded data"};
  app.require_subcommand(1);
  fleetmem::eval::LifelongOptions options;
  options.server_binary = BesideThisProgram("fleetmem-server");
  CLI::App* lifelong = app.add_subcommand(
      "lifelong",
      "BioSLAM's lifelong protocol on a Nordland-layout data root (summer areas 1-3, then "
      "winter areas 1-3); writes summary.csv, curves.csv, curves.png, fleet.csv");
  lifelong->add_option("--data-root", options.data_root,
                       "folder with nordland/{summer,winter}/images-NNNNN.png")
      ->required()
      ->check(CLI::ExistingDirectory);
  lifelong->add_option("--out", options.out_dir, "output folder (created)")->required();
  lifelong->add_flag("--quick", options.quick, "quick settings (under 10 minutes on 2 cores)");
  lifelong->add_option("--methods", options.methods,
                       "methods to run (default all): " +
                           absl::StrJoin(fleetmem::eval::LifelongMethodNames(), ", "))
      ->delimiter(',');
  lifelong->add_option("--seed", options.seed, "seed of every generator")->capture_default_str();
  lifelong->add_option("--threads", options.threads, "torch intra-op threads")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  lifelong->add_option("--server-binary", options.server_binary,
                       "fleetmem-server to run (default: beside this program)")
      ->capture_default_str();
  lifelong->add_option("--code-dimension", options.code_dimension,
                       "D of the GPL memory codes (a multiple of 32)")
      ->capture_default_str();
  lifelong->add_option("--pretrain-steps", options.pretrain_steps,
                       "override: L_joint steps of the encoder's pre-training");
  lifelong->add_option("--steps-per-segment", options.steps_per_segment,
                       "override: place-head steps per segment");
  lifelong->add_option("--negative-candidates", options.negative_candidates,
                       "override: negatives drawn per anchor (the nearest is used)");
  lifelong->add_option("--head-lr", options.head_learning_rate,
                       "override: Adam learning rate of the place head");
  lifelong->add_option("--gan-weight", options.gan_weight,
                       "override: weight of L_gan in the decoder's loss");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? 0 : 2;
  }
  const absl::Status status = fleetmem::eval::RunLifelong(options);
  if (!status.ok()) {
    std::fprintf(stderr, "fleetmem-eval lifelong: %s\n", status.ToString().c_str());
    return 1;
  }
  return 0;
}
