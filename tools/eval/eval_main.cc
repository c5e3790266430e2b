// fleetmem-eval: evaluations of the robot side on recorded data.
//
//   fleetmem-eval lifelong --data-root DIR --out DIR [--quick] [--places N]
//       BioSLAM's lifelong place-recognition protocol, every method
//       (tools/eval/lifelong.h, docs/results.md).
//   fleetmem-eval pretrain --images DIR --out FILE [--first N --count N]
//       A fleet's GPL model: the encoder trained on one domain's frames and
//       frozen (clients/robot/learning/pretrain.h), for fleetmem-robot
//       --gpl-model.
//   fleetmem-eval trajectory --reference FILE --estimate FILE
//       [--format kitti|tum] [--align se3|sim3|none] [--rpe-delta-m D]
//       [--json]
//       ATE, RPE and KITTI t_err/r_err of an estimate (docs/slam.md).
//   fleetmem-eval relations --estimate FILE --relations FILE [--json]
//       The Freiburg relations metric of a 2-D SLAM estimate.
//   fleetmem-eval continual --table FILE [--json]
//       CL-SLAM's AQ/RQ from a table of deployments.
//   fleetmem-eval continual-vo --data-root DIR --out DIR [--quick] [--frames N]
//       CL-SLAM's continual visual odometry on the KITTI clips, every
//       method, AQ/RQ (tools/eval/continual_vo_eval.h).
//   fleetmem-eval slam --log FILE --relations FILE --out DIR [--scans N]
//       The laser SLAM back end on a CARMEN log, scored by the relations
//       metric (tools/eval/slam_eval.h).
//
// Exit codes: 0 done, 1 the run failed (message on stderr), 2 bad usage.
#include <unistd.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "CLI/CLI.hpp"
#include "absl/strings/str_join.h"
#include "clients/robot/learning/pretrain.h"
#include "clients/robot/sensing/nordland.h"
#include "fleetmem_version.h"
#include "services/common/cli_program.h"
#include "tools/eval/continual_vo_eval.h"
#include "tools/eval/lifelong.h"
#include "tools/eval/slam_eval.h"
#include "tools/eval/trajectory_eval.h"

namespace {

std::string BesideThisProgram(const std::string& name) {
  std::error_code ec;
  const std::filesystem::path self =
      std::filesystem::read_symlink("/proc/self/exe", ec);
  if (ec) return name;
  return (self.parent_path() / name).string();
}

// lifelong's flags: the protocol's, and the learners' overrides.
void AddLifelongFlags(CLI::App* sub, fleetmem::eval::LifelongOptions& options) {
  sub->add_option("--data-root", options.data_root,
                  "folder with nordland/{summer,winter}/images-NNNNN.png")
      ->required()
      ->check(CLI::ExistingDirectory);
  sub->add_option("--out", options.out_dir, "output folder (created)")
      ->required();
  sub->add_flag("--quick", options.quick,
                "quick settings (under 10 minutes on 2 cores)");
  sub->add_option(
         "--methods", options.methods,
         "methods to run (default all): " +
             absl::StrJoin(fleetmem::eval::LifelongMethodNames(), ", "))
      ->delimiter(',');
  sub->add_option("--seed", options.seed, "seed of every generator")
      ->capture_default_str();
  sub->add_option("--threads", options.threads, "torch intra-op threads")
      ->capture_default_str()
      ->check(CLI::Range(1, 64));
  sub->add_option("--server-binary", options.server_binary,
                  "fleetmem-server to run (default: beside this program)");
  sub->add_option("--code-dimension", options.code_dimension,
                  "D of the GPL memory codes (a multiple of 32)")
      ->capture_default_str();
  sub->add_option("--places", options.max_places,
                  "only the first N places of the route (0 = all; the test "
                  "suite's smoke run uses a few dozen)")
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--skip-places", options.skip_places,
                  "places skipped at the start of the route (a stretch no "
                  "setting was tuned on: the hold-out route)")
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--seeds", options.seeds,
                  "runs of every method with seeds --seed, --seed+1, ... "
                  "(0 = 1 quick, 3 full); the report gives mean and spread")
      ->check(CLI::NonNegativeNumber);
}

void AddLifelongOverrides(CLI::App* sub,
                          fleetmem::eval::LifelongOptions& options) {
  sub->add_option("--pretrain-steps", options.pretrain_steps,
                  "override: L_joint steps of the encoder's pre-training");
  sub->add_option("--steps-per-segment", options.steps_per_segment,
                  "override: place-head steps per segment");
  sub->add_option("--end-to-end-steps", options.end_to_end_steps,
                  "override: gpl_e2e_joint's L_joint steps (150 quick, "
                  "1200 full)")
      ->check(CLI::PositiveNumber);
  sub->add_option("--negative-candidates", options.negative_candidates,
                  "override: negatives drawn per anchor (the nearest is used)");
  sub->add_option("--head-lr", options.head_learning_rate,
                  "override: Adam learning rate of the place head");
  sub->add_option("--gan-weight", options.gan_weight,
                  "override: weight of L_gan in the decoder's loss");
  sub->add_option("--metric-update-rate", options.metric_update_rate,
                  "override: the metric head's update rate per segment, in "
                  "(0, 1]")
      ->check(CLI::Range(1e-9, 1.0));
  sub->add_option("--metric-partners", options.metric_partners,
                  "override: the metric head's partners per sample (>= 1)")
      ->check(CLI::PositiveNumber);
  sub->add_option("--spatial-scale", options.spatial_scale,
                  "override: the fleet memory's spatial_scale_m (place "
                  "units that weigh like one unit of code distance; > 0)")
      ->check(CLI::PositiveNumber);
  sub->add_option("--sequence-candidates", options.sequence_candidates,
                  "*_seq_robot: map places per frame in the robot's "
                  "sequence search")
      ->capture_default_str()
      ->check(CLI::Range(1, 1000));
}

// pretrain's flags.
struct PretrainFlags {
  std::string images, out, version = "gpl-64x32-d256-v1";
  size_t first = 0, count = 0;
  int steps = 1000, code_dimension = 256, threads = 2;
  uint64_t seed = 1;
};

CLI::App* AddPretrain(CLI::App& app, PretrainFlags& pre) {
  CLI::App* sub = app.add_subcommand(
      "pretrain",
      "train a fleet's GPL model on one domain's frames (images-NNNNN.png)");
  sub->add_option("--images", pre.images, "folder of images-NNNNN.png frames")
      ->required()
      ->check(CLI::ExistingDirectory);
  sub->add_option("--out", pre.out, "model file to write")->required();
  sub->add_option("--first", pre.first, "first frame (index in file order)");
  sub->add_option("--count", pre.count, "frames to use (0 = all)");
  sub->add_option("--steps", pre.steps, "L_joint steps")->capture_default_str();
  sub->add_option("--code-dimension", pre.code_dimension, "D")
      ->capture_default_str();
  sub->add_option("--version", pre.version, "encoder version the codes carry")
      ->capture_default_str();
  sub->add_option("--seed", pre.seed, "seed")->capture_default_str();
  sub->add_option("--threads", pre.threads, "torch threads")
      ->capture_default_str();
  return sub;
}

CLI::App* AddTrajectory(CLI::App& app,
                        fleetmem::eval::TrajectoryEvalOptions& traj) {
  CLI::App* sub = app.add_subcommand(
      "trajectory",
      "ATE (after SE(3)/Sim(3) alignment), RPE and KITTI t_err/r_err of an "
      "estimate against a reference (KITTI or TUM files)");
  sub->add_option("--reference", traj.reference, "ground truth file")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--estimate", traj.estimate, "estimated trajectory")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--format", traj.format,
                  "kitti or tum (default: detected from the files)")
      ->check(CLI::IsMember({"kitti", "tum"}));
  sub->add_option("--align", traj.align, "ATE alignment")
      ->capture_default_str()
      ->check(CLI::IsMember({"se3", "sim3", "none"}));
  sub->add_option("--rpe-delta-m", traj.rpe_delta_m,
                  "RPE pairs by this path length in metres (default: by "
                  "--rpe-delta-frames)")
      ->check(CLI::PositiveNumber);
  sub->add_option("--rpe-delta-frames", traj.rpe_delta_frames,
                  "RPE pairs every this many frames")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  sub->add_flag("--pairs-from-reference", traj.pairs_from_reference,
                "form RPE pairs on the reference's path (evo's "
                "--pairs_from_reference; default: the estimate's)");
  sub->add_option("--max-time-diff", traj.max_time_diff_s,
                  "largest time difference of associated TUM poses (s)")
      ->capture_default_str();
  sub->add_flag("--json", traj.json, "print JSON");
  return sub;
}

CLI::App* AddRelations(CLI::App& app,
                       fleetmem::eval::RelationsEvalOptions& rel) {
  CLI::App* sub = app.add_subcommand(
      "relations",
      "the Freiburg relations metric (Kuemmerle et al. 2009) of a 2-D SLAM "
      "estimate (TUM file, timestamps of the scans)");
  sub->add_option("--estimate", rel.estimate, "estimated trajectory")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--relations", rel.relations, "relations file")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--max-time-diff", rel.max_time_diff_s,
                  "largest difference of a relation's time from a pose's")
      ->capture_default_str();
  sub->add_flag("--json", rel.json, "print JSON");
  return sub;
}

CLI::App* AddContinual(CLI::App& app, std::string& continual_table,
                       bool& continual_json) {
  CLI::App* sub = app.add_subcommand(
      "continual",
      "CL-SLAM's adaptation and retention quality (AQ, RQ) from a CSV of "
      "deployments: sequence (scenes joined by '>'), t_err, r_err");
  sub->add_option("--table", continual_table, "deployments CSV")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_flag("--json", continual_json, "print JSON");
  return sub;
}

CLI::App* AddSlam(CLI::App& app,
                  fleetmem::eval::SlamEvalOptions& slam_options) {
  CLI::App* sub = app.add_subcommand(
      "slam",
      "the laser SLAM back end on a CARMEN log (raw odometry, scan matching, "
      "loops from the robot's own memory), scored by a relations file");
  sub->add_option("--log", slam_options.log, "CARMEN log (.clf or .clf.bz2)")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--relations", slam_options.relations, "relations file")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--out", slam_options.out_dir, "output folder (created)")
      ->required();
  sub->add_option("--candidates", slam_options.candidates,
                  "loop candidates per keyframe")
      ->capture_default_str();
  sub->add_option("--prior-radius", slam_options.prior_radius_m,
                  "position prior of own candidates (m)")
      ->capture_default_str();
  sub->add_option("--scans", slam_options.max_scans,
                  "only the first N scans of the log (0 = all)")
      ->check(CLI::NonNegativeNumber);
  return sub;
}

CLI::App* AddContinualVo(CLI::App& app,
                         fleetmem::eval::ContinualVoEvalOptions& vo_options) {
  CLI::App* sub = app.add_subcommand(
      "continual-vo",
      "CL-SLAM's continual visual odometry on the real KITTI clips: "
      "pre-training, deployments in sequence, every method, AQ/RQ "
      "(docs/continual-vo.md)");
  sub->add_option("--data-root", vo_options.data_root,
                  "folder holding kitti/clip1 and kitti/clip2")
      ->required()
      ->check(CLI::ExistingDirectory);
  sub->add_option("--out", vo_options.out_dir, "output folder (created)")
      ->required();
  sub->add_flag("--quick", vo_options.quick,
                "one order and a shorter pre-training");
  sub->add_option("--pretrain-steps", vo_options.pretrain_steps,
                  "pre-training steps (0: 1500 quick, 4000 full)")
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--update-steps", vo_options.update_steps,
                  "c, update steps per new frame")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  sub->add_option("--threads", vo_options.threads, "torch intra-op threads")
      ->capture_default_str()
      ->check(CLI::PositiveNumber);
  sub->add_option("--seed", vo_options.seed, "seed")->capture_default_str();
  sub->add_option("--frames", vo_options.frames,
                  "only the first N frames of each clip (0 = all; the test "
                  "suite's smoke run uses two dozen)")
      ->check(CLI::NonNegativeNumber);
  return sub;
}

// A fleet's GPL model trained on `pre.images`' frames, written to pre.out.
absl::Status RunPretrain(const PretrainFlags& pre) {
  namespace gpl = fleetmem::robot::gpl;
  gpl::SetTorchThreads(pre.threads);
  absl::StatusOr<std::vector<int>> frames =
      fleetmem::robot::ListNordlandFrames(pre.images);
  if (!frames.ok()) return frames.status();
  const size_t end = pre.count == 0
                         ? frames->size()
                         : std::min(frames->size(), pre.first + pre.count);
  std::vector<cv::Mat> images;
  std::vector<double> positions;
  for (size_t i = pre.first; i < end; ++i) {
    absl::StatusOr<cv::Mat> image =
        fleetmem::robot::LoadNordlandGrey(pre.images, (*frames)[i]);
    if (!image.ok()) return image.status();
    images.push_back(*std::move(image));
    positions.push_back((*frames)[i]);
  }
  gpl::PretrainOptions options;
  options.model.code_dimension = pre.code_dimension;
  options.model.seed = pre.seed;
  options.version = pre.version;
  options.steps = pre.steps;
  options.seed = pre.seed;
  options.log = [](std::string_view line) {
    std::fprintf(stderr, "%.*s\n", int(line.size()), line.data());
  };
  absl::StatusOr<std::unique_ptr<gpl::GplModel>> model =
      gpl::PretrainFleetEncoder(images, positions, options);
  absl::Status saved = model.ok() ? (*model)->Save(pre.out) : model.status();
  if (!saved.ok()) return saved;
  std::fprintf(
      stderr, "fleetmem-eval pretrain: %s (%lld parameters) written to %s\n",
      pre.version.c_str(), static_cast<long long>((*model)->ParameterCount()),
      pre.out.c_str());
  return absl::OkStatus();
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{
      "fleetmem-eval: evaluations of fleetmem's robot side on recorded data."};
  fleetmem::common::SetUpProgram(app, "fleetmem-eval");
  app.require_subcommand(1);
  fleetmem::eval::LifelongOptions options;
  options.server_binary = BesideThisProgram("fleetmem-server");
  CLI::App* lifelong =
      app.add_subcommand("lifelong",
                         "BioSLAM's lifelong protocol on a Nordland-layout "
                         "data root (summer areas 1-3, then "
                         "winter areas 1-3; protocol v2: winter queries of "
                         "held-out places against the summer map); writes "
                         "summary.csv, summary.md, curves.csv, curves.png, "
                         "memory.csv, fleet.csv");
  AddLifelongFlags(lifelong, options);
  AddLifelongOverrides(lifelong, options);
  PretrainFlags pre;
  CLI::App* pretrain = AddPretrain(app, pre);
  fleetmem::eval::TrajectoryEvalOptions traj;
  CLI::App* trajectory = AddTrajectory(app, traj);
  fleetmem::eval::RelationsEvalOptions rel;
  CLI::App* relations = AddRelations(app, rel);
  std::string continual_table;
  bool continual_json = false;
  CLI::App* continual = AddContinual(app, continual_table, continual_json);
  fleetmem::eval::SlamEvalOptions slam_options;
  CLI::App* slam = AddSlam(app, slam_options);
  fleetmem::eval::ContinualVoEvalOptions vo_options;
  CLI::App* continual_vo = AddContinualVo(app, vo_options);
  if (std::optional<int> done =
          fleetmem::common::ParseProgram(app, argc, argv)) {
    return *done;
  }
  const char* what = "fleetmem-eval";
  absl::Status status;
  if (continual_vo->parsed()) {
    status = fleetmem::eval::RunContinualVoEval(vo_options);
  } else if (slam->parsed()) {
    status = fleetmem::eval::RunSlamEval(slam_options);
  } else if (trajectory->parsed()) {
    status = fleetmem::eval::RunTrajectoryEval(traj);
  } else if (relations->parsed()) {
    status = fleetmem::eval::RunRelationsEval(rel);
  } else if (continual->parsed()) {
    status =
        fleetmem::eval::RunContinualScores(continual_table, continual_json);
  } else if (pretrain->parsed()) {
    what = "fleetmem-eval pretrain";
    status = RunPretrain(pre);
  } else {
    what = "fleetmem-eval lifelong";
    status = fleetmem::eval::RunLifelong(options);
  }
  if (!status.ok()) {
    std::fprintf(stderr, "%s: %s\n", what, status.ToString().c_str());
    return 1;
  }
  return 0;
}
