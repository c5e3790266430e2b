#include "clients/robot/vo/vo_deployment.h"

#include <filesystem>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "services/common/files.h"
#include "clients/robot/slam/trajectory_metrics.h"

namespace fleetmem::vo {
namespace {

namespace fs = std::filesystem;

absl::Status WriteBoth(const std::string& stem, const slam::Trajectory& t) {
  if (absl::Status s = files::WriteFile(
          stem + ".kitti",
          slam::FormatTrajectory(t, slam::TrajectoryFormat::kKitti));
      !s.ok()) {
    return s;
  }
  return files::WriteFile(
      stem + ".tum", slam::FormatTrajectory(t, slam::TrajectoryFormat::kTum));
}

}  // namespace

absl::StatusOr<VoDeploymentReport> RunVoDeployment(
    const VoDeploymentOptions& options,
    const std::function<void(size_t, size_t)>& progress) {
  const std::string weights_path = options.data_dir + "/vo-weights.pt";
  const bool resume = fs::exists(weights_path);
  if (!resume && options.initial_model.empty()) {
    return absl::NotFoundError(absl::StrCat(
        "no ", weights_path,
        " and no initial model: pass the fleet's "
        "pre-trained weights (fleetmem-eval continual-vo writes them)"));
  }
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> model =
      DepthPoseModel::Load(resume ? weights_path : options.initial_model);
  if (!model.ok()) return model.status();
  const DepthPoseOptions& mo = (*model)->options();
  absl::StatusOr<KittiClip> clip =
      LoadKittiClip(options.sequence_dir, mo.image_width, mo.image_height);
  if (!clip.ok()) return clip.status();
  const std::string environment =
      options.environment.empty() ? clip->name : options.environment;

  absl::StatusOr<std::unique_ptr<ContinualVo>> vo =
      ContinualVo::Create(**model, options.method, options.vo);
  if (!vo.ok()) return vo.status();
  absl::StatusOr<DeploymentResult> result =
      (*vo)->Deploy(environment, *clip, progress);
  if (!result.ok()) return result.status();

  int n = 1;
  while (
      fs::exists(absl::StrCat(options.data_dir, "/vo/", environment, "-", n))) {
    ++n;
  }
  VoDeploymentReport report;
  report.out_dir = absl::StrCat(options.data_dir, "/vo/", environment, "-", n);
  std::error_code ec;
  fs::create_directories(report.out_dir, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create ", report.out_dir, ": ", ec.message()));
  }
  if (absl::Status s =
          WriteBoth(report.out_dir + "/trajectory", result->optimized);
      !s.ok()) {
    return s;
  }
  if (absl::Status s =
          WriteBoth(report.out_dir + "/odometry", result->odometry);
      !s.ok()) {
    return s;
  }
  absl::StatusOr<slam::AteResult> ate = slam::AbsoluteTrajectoryError(
      clip->ground_truth, result->optimized, slam::Alignment::kSe3);
  if (ate.ok()) report.ate_se3_m = ate->translation_m.rmse;
  const std::string json = absl::StrFormat(
      "{\"environment\": \"%s\", \"method\": \"%s\", \"deployment\": %d, "
      "\"frames\": %zu, \"adapted_frames\": %d, \"skipped_frames\": %d, "
      "\"update_steps\": %d, \"loops\": %d, \"seconds\": %.3f, "
      "\"ate_se3_m\": %.6f, \"started_from\": \"%s\"}\n",
      environment, VoMethodName(options.method), n, clip->left.size(),
      result->adapted_frames, result->skipped_frames, result->update_steps,
      result->loops, result->seconds, report.ate_se3_m,
      resume ? weights_path : options.initial_model);
  if (absl::Status s = files::WriteFile(report.out_dir + "/vo.json", json);
      !s.ok()) {
    return s;
  }
  // Last: the weights that start the next deployment.
  if (absl::Status s = (*vo)->weights().Save(weights_path); !s.ok()) return s;
  report.result = *std::move(result);
  return report;
}

}  // namespace fleetmem::vo
