#include "tools/eval/slam_eval.h"

#include <chrono>
#include <cstdio>
#include <filesystem>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/sensing/carmen_log.h"
#include "clients/robot/sensing/code_search.h"
#include "clients/robot/sensing/scan_encoder.h"
#include "clients/robot/slam/laser_slam.h"
#include "clients/robot/slam/trajectory_metrics.h"
#include "services/common/files.h"

namespace fleetmem::eval {
namespace {

struct VariantResult {
  std::string name;
  slam::RelationsResult relations;
  slam::LaserSlamCounters counters;
  double ms_per_keyframe = 0.0;
};

// What every variant runs on.
struct Inputs {
  std::vector<robot::Observation> scans;
  std::vector<slam::Relation> relations;
  std::unique_ptr<robot::Encoder> encoder;
};

// The log (cut to options.max_scans), the relations, the encoder; the
// output folder made.
absl::StatusOr<Inputs> LoadInputs(const SlamEvalOptions& options) {
  Inputs inputs;
  absl::StatusOr<std::string> log = robot::ReadMaybeBzip2(options.log);
  if (!log.ok()) return log.status();
  absl::StatusOr<std::vector<robot::Observation>> scans =
      robot::ParseCarmenLog(*log, options.log);
  if (!scans.ok()) return scans.status();
  inputs.scans = *std::move(scans);
  if (options.max_scans > 0 &&
      inputs.scans.size() > size_t(options.max_scans)) {
    inputs.scans.resize(options.max_scans);
  }
  absl::StatusOr<std::string> rel_text = files::ReadFile(options.relations);
  if (!rel_text.ok()) return rel_text.status();
  absl::StatusOr<std::vector<slam::Relation>> relations =
      slam::ParseRelations(*rel_text, options.relations);
  if (!relations.ok()) return relations.status();
  inputs.relations = *std::move(relations);
  absl::StatusOr<std::unique_ptr<robot::Encoder>> encoder =
      robot::NewScanEncoderByName(options.encoder);
  if (!encoder.ok()) return encoder.status();
  inputs.encoder = *std::move(encoder);
  std::error_code ec;
  std::filesystem::create_directories(options.out_dir, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create ", options.out_dir, ": ", ec.message()));
  }
  return inputs;
}

// The robot's own memory at keyframe `k` (its scan's code `code`): the
// nearest codes of earlier keyframes, kept if the current estimate puts
// them within the prior's radius, offered as loops.
absl::Status CloseOwnLoops(const SlamEvalOptions& options, size_t k,
                           const std::vector<float>& code,
                           const robot::BruteForceIndex& index,
                           const std::vector<robot::LaserScan>& keyframe_scans,
                           slam::LaserSlam& mapper) {
  std::vector<slam::LoopCandidate> candidates;
  const slam::Pose2 here = mapper.KeyframePose(k);
  for (double label : index.Search(code, 50)) {
    const size_t j = static_cast<size_t>(label);
    const slam::Pose2 there = mapper.KeyframePose(j);
    if (std::hypot(there.x - here.x, there.y - here.y) >
        options.prior_radius_m) {
      continue;
    }
    candidates.push_back(slam::LoopCandidate{"robot-1", mapper.KeyframeTime(j),
                                             there, keyframe_scans[j]});
    if (static_cast<int>(candidates.size()) >= options.candidates) break;
  }
  return mapper.CloseLoops(k, candidates).status();
}

// One variant over the log: its trajectory (.tum) and map (.png) written,
// its error against the relations.
absl::StatusOr<VariantResult> RunVariant(const std::string& variant,
                                         const Inputs& inputs,
                                         const SlamEvalOptions& options) {
  slam::LaserSlam mapper("robot-1", {});
  robot::BruteForceIndex index(inputs.encoder->dimension());
  std::vector<robot::LaserScan> keyframe_scans;
  const auto start = std::chrono::steady_clock::now();
  for (const robot::Observation& o : inputs.scans) {
    std::optional<size_t> k = mapper.AddScan(
        o.timestamp_ns, slam::Pose2{o.place.x, o.place.y, o.place.yaw}, o.scan);
    if (!k || variant != "own_memory_loops") continue;
    absl::StatusOr<std::vector<float>> code = inputs.encoder->Encode(o);
    if (!code.ok()) return code.status();
    if (absl::Status closed =
            CloseOwnLoops(options, *k, *code, index, keyframe_scans, mapper);
        !closed.ok()) {
      return closed;
    }
    index.Add(*code, static_cast<double>(*k));
    keyframe_scans.push_back(o.scan);
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  const slam::Trajectory trajectory = variant == "odometry"
                                          ? mapper.OdometryTrajectory()
                                          : mapper.ScanTrajectory();
  absl::StatusOr<slam::RelationsResult> r =
      slam::RelationsError(trajectory, inputs.relations, 1e-3);
  if (!r.ok()) return r.status();
  const std::string stem = absl::StrCat(options.out_dir, "/", variant);
  if (absl::Status s = files::WriteFile(
          stem + ".tum",
          slam::FormatTrajectory(trajectory, slam::TrajectoryFormat::kTum));
      !s.ok()) {
    return s;
  }
  if (absl::Status s = slam::WriteOccupancyPng(
          mapper.MapScans(/*at_odometry=*/variant == "odometry"), 0.1,
          stem + ".png");
      !s.ok()) {
    return s;
  }
  VariantResult v{
      variant, *r, mapper.counters(),
      1000.0 * seconds / std::max<uint64_t>(1, mapper.counters().keyframes)};
  std::fprintf(stderr,
               "slam %-17s relations %.3f +- %.3f m, %.2f +- %.2f deg; "
               "%llu keyframes, %.1f ms per keyframe\n",
               variant.c_str(), r->translation_m.mean, r->translation_m.std,
               r->rotation_deg.mean, r->rotation_deg.std,
               static_cast<unsigned long long>(v.counters.keyframes),
               v.ms_per_keyframe);
  return v;
}

// The results as a table on stdout and as summary.csv.
absl::Status Report(const std::vector<VariantResult>& results,
                    const std::string& out_dir) {
  std::string csv =
      "variant,relations,trans_mean_m,trans_std_m,rot_mean_deg,rot_std_deg,"
      "keyframes,odometry_matched,loops_proposed,loops_accepted,"
      "loops_rejected_geometry,loops_rejected_graph,ms_per_keyframe\n";
  std::printf(
      "| variant | translation (m) | rotation (deg) | keyframes | "
      "loops proposed | accepted | rejected (geometry) | rejected "
      "(graph) | ms per keyframe |\n|---|---|---|---|---|---|---|---|"
      "---|\n");
  for (const VariantResult& v : results) {
    const auto& c = v.counters;
    absl::StrAppendFormat(
        &csv, "%s,%d,%.4f,%.4f,%.4f,%.4f,%d,%d,%d,%d,%d,%d,%.2f\n", v.name,
        v.relations.translation_m.count, v.relations.translation_m.mean,
        v.relations.translation_m.std, v.relations.rotation_deg.mean,
        v.relations.rotation_deg.std, c.keyframes, c.odometry_matched,
        c.loops_proposed, c.loops_accepted, c.loops_rejected_geometry,
        c.loops_rejected_graph, v.ms_per_keyframe);
    std::printf(
        "| %s | %.3f +- %.3f | %.2f +- %.2f | %llu | %llu | %llu | "
        "%llu | %llu | %.1f |\n",
        v.name.c_str(), v.relations.translation_m.mean,
        v.relations.translation_m.std, v.relations.rotation_deg.mean,
        v.relations.rotation_deg.std,
        static_cast<unsigned long long>(c.keyframes),
        static_cast<unsigned long long>(c.loops_proposed),
        static_cast<unsigned long long>(c.loops_accepted),
        static_cast<unsigned long long>(c.loops_rejected_geometry),
        static_cast<unsigned long long>(c.loops_rejected_graph),
        v.ms_per_keyframe);
  }
  return files::WriteFile(out_dir + "/summary.csv", csv);
}

}  // namespace

absl::Status RunSlamEval(const SlamEvalOptions& options) {
  absl::StatusOr<Inputs> inputs = LoadInputs(options);
  if (!inputs.ok()) return inputs.status();
  std::vector<VariantResult> results;
  for (const std::string variant :
       {"odometry", "scan_matching", "own_memory_loops"}) {
    absl::StatusOr<VariantResult> result =
        RunVariant(variant, *inputs, options);
    if (!result.ok()) return result.status();
    results.push_back(*std::move(result));
  }
  return Report(results, options.out_dir);
}

}  // namespace fleetmem::eval
