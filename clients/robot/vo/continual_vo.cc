#include "clients/robot/vo/continual_vo.h"

#include <chrono>

#include "absl/strings/str_cat.h"
#include "clients/robot/slam/pose_graph.h"
#include "services/core/feature_space.h"

namespace fleetmem::vo {
namespace {

// Distance travelled from frame a to frame b > a.
double Travelled(const KittiClip& clip, size_t a, size_t b) {
  double d = 0.0;
  for (size_t i = a + 1; i <= b; ++i) d += clip.travelled_m[i];
  return d;
}

slam::Trajectory Stamped(const KittiClip& clip,
                         const std::vector<Eigen::Isometry3d>& poses) {
  slam::Trajectory t;
  for (size_t i = 0; i < poses.size(); ++i) {
    t.push_back({i * clip.frame_interval_s, poses[i]});
  }
  return t;
}

// Information of an odometry or loop edge: 0.1 m and ~1 degree.
slam::PoseGraph3d::Information EdgeInformation() {
  slam::PoseGraph3d::Information info =
      slam::PoseGraph3d::Information::Identity();
  info.topLeftCorner<3, 3>() *= 100.0;
  info.bottomRightCorner<3, 3>() *= 3000.0;
  return info;
}

}  // namespace

absl::StatusOr<VoMethod> ParseVoMethod(std::string_view name) {
  if (name == "fixed") return VoMethod::kFixed;
  if (name == "expert_only") return VoMethod::kExpertOnly;
  if (name == "generalizer_only") return VoMethod::kGeneralizerOnly;
  if (name == "cl_slam") return VoMethod::kClSlam;
  return absl::InvalidArgumentError(
      absl::StrCat("unknown method '", std::string(name),
                   "' (fixed, expert_only, generalizer_only or cl_slam)"));
}

std::string VoMethodName(VoMethod method) {
  switch (method) {
    case VoMethod::kFixed:
      return "fixed";
    case VoMethod::kExpertOnly:
      return "expert_only";
    case VoMethod::kGeneralizerOnly:
      return "generalizer_only";
    case VoMethod::kClSlam:
      return "cl_slam";
  }
  return "?";
}

Triplet ClipTriplet(const KittiClip& clip, size_t a, size_t b, size_t c) {
  Triplet t;
  t.images = {clip.left[a], clip.left[b], clip.left[c]};
  t.distances_m = {Travelled(clip, a, b), Travelled(clip, b, c)};
  t.camera = clip.camera;
  return t;
}

absl::StatusOr<VoLosses> Pretrain(
    DepthPoseModel& model, const KittiClip& clip,
    const PretrainOptions& options,
    const std::function<void(int, const VoLosses&)>& progress) {
  if (clip.left.size() < 3) {
    return absl::InvalidArgumentError(absl::StrCat(
        "pre-training needs 3 frames; ", clip.name, " has ", clip.left.size()));
  }
  if (options.steps < 0 || options.batch_size <= 0) {
    return absl::InvalidArgumentError("steps >= 0 and batch_size > 0");
  }
  std::mt19937_64 rng(options.seed);
  std::uniform_int_distribution<size_t> middle(1, clip.left.size() - 2);
  VoLosses last;
  for (int step = 0; step < options.steps; ++step) {
    std::vector<Triplet> batch;
    for (int i = 0; i < options.batch_size; ++i) {
      const size_t m = middle(rng);
      Triplet t = ClipTriplet(clip, m - 1, m, m + 1);
      if (options.stereo && !clip.right.empty())
        t.right_of_middle = clip.right[m];
      batch.push_back(std::move(t));
    }
    absl::StatusOr<VoLosses> losses = model.TrainStep(batch);
    if (!losses.ok()) return losses.status();
    last = *losses;
    if (progress) progress(step, last);
  }
  model.FreezeEncoders();
  return last;
}

ContinualVo::ContinualVo(std::unique_ptr<DepthPoseModel> weights,
                         VoMethod method, const ContinualVoOptions& options)
    : weights_(std::move(weights)),
      method_(method),
      options_(options),
      replay_(options.replay),
      rng_(options.seed) {}

absl::StatusOr<std::unique_ptr<ContinualVo>> ContinualVo::Create(
    const DepthPoseModel& initial, VoMethod method,
    const ContinualVoOptions& options) {
  if (options.update_steps < 0 || options.min_motion_m < 0.0) {
    return absl::InvalidArgumentError(
        "update_steps and min_motion_m must be >= 0");
  }
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> copy = initial.Clone();
  if (!copy.ok()) return copy.status();
  if (!(*copy)->encoders_frozen()) (*copy)->FreezeEncoders();
  return std::unique_ptr<ContinualVo>(
      new ContinualVo(std::move(*copy), method, options));
}

absl::StatusOr<std::unique_ptr<ContinualVo>> ContinualVo::Clone() const {
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> copy = weights_->Clone();
  if (!copy.ok()) return copy.status();
  std::unique_ptr<ContinualVo> clone(
      new ContinualVo(std::move(*copy), method_, options_));
  clone->replay_ = replay_;
  clone->rng_ = rng_;
  return clone;
}

absl::Status ContinualVo::Remember(const std::string& environment,
                                   const KittiClip& clip) {
  for (size_t m = 1; m + 1 < clip.left.size(); ++m) {
    absl::StatusOr<std::vector<float>> feature =
        weights_->Feature(clip.left[m]);
    if (!feature.ok()) return feature.status();
    replay_.Offer(environment, *feature, ClipTriplet(clip, m - 1, m, m + 1));
  }
  return absl::OkStatus();
}

absl::Status ContinualVo::Adapt(const std::string& environment,
                                const Triplet& online, DepthPoseModel* expert,
                                DepthPoseModel* generalizer,
                                DeploymentResult& result) {
  for (int step = 0; step < options_.update_steps; ++step) {
    if (expert != nullptr) {
      absl::StatusOr<VoLosses> l = expert->TrainStep({&online, 1});
      if (!l.ok()) return l.status();
      result.last_losses = *l;
    }
    if (generalizer != nullptr) {
      std::vector<Triplet> batch = {online};
      for (Triplet& t : replay_.DrawOthers(environment, rng_)) {
        batch.push_back(std::move(t));
      }
      absl::StatusOr<VoLosses> l = generalizer->TrainStep(batch);
      if (!l.ok()) return l.status();
      if (expert == nullptr) result.last_losses = *l;
    }
    ++result.update_steps;
  }
  ++result.adapted_frames;
  return absl::OkStatus();
}

absl::StatusOr<size_t> ContinualVo::AddLoops(
    const KittiClip& clip, const std::vector<std::vector<float>>& features,
    size_t i, DepthPoseModel& odometer, slam::PoseGraph3d& graph) const {
  size_t loops = 0;
  for (size_t j = 0; j + options_.loop_min_gap_frames <= i; ++j) {
    double dot = 0.0;
    for (size_t d = 0; d < features[i].size(); ++d) {
      dot += double(features[i][d]) * features[j][d];
    }
    if (dot < options_.loop_similarity) continue;
    absl::StatusOr<Eigen::Isometry3d> relative =
        odometer.PredictMotion(clip.left[j], clip.left[i]);
    if (!relative.ok()) return relative.status();
    if (graph.AddEdge(j, i, *relative, EdgeInformation(), slam::EdgeKind::kLoop)
            .ok()) {
      ++loops;
    }
  }
  return loops;
}

absl::Status ContinualVo::CloneModels(
    std::unique_ptr<DepthPoseModel>& expert,
    std::unique_ptr<DepthPoseModel>& generalizer) const {
  if (method_ != VoMethod::kGeneralizerOnly) {
    absl::StatusOr<std::unique_ptr<DepthPoseModel>> m = weights_->Clone();
    if (!m.ok()) return m.status();
    expert = std::move(*m);
  }
  if (method_ == VoMethod::kGeneralizerOnly || method_ == VoMethod::kClSlam) {
    absl::StatusOr<std::unique_ptr<DepthPoseModel>> m = weights_->Clone();
    if (!m.ok()) return m.status();
    generalizer = std::move(*m);
  }
  return absl::OkStatus();
}

// Long (90 lines): one frame loop in CL-SLAM's order — adapt on the newest
// triplet, odometry from the last accepted frame, loop edges — whose state
// (poses, features, accepted frames, the graph) each step reads; its
// steps with a state of their own are Adapt and AddLoops.
absl::StatusOr<DeploymentResult> ContinualVo::Deploy(
    const std::string& environment, const KittiClip& clip,
    const std::function<void(size_t, size_t)>& progress) {
  const auto start = std::chrono::steady_clock::now();
  const bool adapts = method_ != VoMethod::kFixed;
  std::unique_ptr<DepthPoseModel> expert, generalizer;
  if (absl::Status cloned = CloneModels(expert, generalizer); !cloned.ok()) {
    return cloned;
  }
  DepthPoseModel& odometer = expert != nullptr ? *expert : *generalizer;

  const size_t n = clip.left.size();
  DeploymentResult result;
  std::vector<Eigen::Isometry3d> poses(n, Eigen::Isometry3d::Identity());
  std::vector<Eigen::Isometry3d> generalizer_poses = poses;
  std::vector<std::vector<float>> features;
  slam::PoseGraph3d graph;
  std::vector<size_t> accepted;
  for (size_t i = 0; i < n; ++i) {
    if (progress) progress(i, n);
    absl::StatusOr<std::vector<float>> feature =
        weights_->Feature(clip.left[i]);
    if (!feature.ok()) return feature.status();
    features.push_back(core::NormalizedCode(*feature));
    if (i == 0) {
      accepted.push_back(0);
      graph.AddNode(poses[0]);
      continue;
    }
    const size_t last = accepted.back();
    const bool skip = Travelled(clip, last, i) < options_.min_motion_m;
    if (skip) {
      ++result.skipped_frames;
    } else {
      accepted.push_back(i);
    }
    if (!skip && adapts && accepted.size() >= 3) {
      const size_t k = accepted.size();
      const Triplet online =
          ClipTriplet(clip, accepted[k - 3], accepted[k - 2], accepted[k - 1]);
      if (absl::Status adapted = Adapt(environment, online, expert.get(),
                                       generalizer.get(), result);
          !adapted.ok()) {
        return adapted;
      }
      if (generalizer) {
        replay_.Offer(environment, features[accepted[k - 2]], online);
      }
    }
    // Odometry from the last accepted frame before this one.
    const size_t from = skip ? last : accepted[accepted.size() - 2];
    absl::StatusOr<Eigen::Isometry3d> motion =
        odometer.PredictMotion(clip.left[from], clip.left[i]);
    if (!motion.ok()) return motion.status();
    poses[i] = poses[from] * *motion;
    if (method_ == VoMethod::kClSlam) {
      absl::StatusOr<Eigen::Isometry3d> g =
          generalizer->PredictMotion(clip.left[from], clip.left[i]);
      if (!g.ok()) return g.status();
      generalizer_poses[i] = generalizer_poses[from] * *g;
    }
    graph.AddNode(poses[i]);
    if (absl::Status s = graph.AddEdge(from, i, *motion, EdgeInformation(),
                                       slam::EdgeKind::kOdometry);
        !s.ok()) {
      return s;
    }
    absl::StatusOr<size_t> loops = AddLoops(clip, features, i, odometer, graph);
    if (!loops.ok()) return loops.status();
    result.loops += *loops;
    if (*loops > 0) {
      absl::StatusOr<slam::SolveReport> solved = graph.Optimize();
      if (!solved.ok()) return solved.status();
    }
  }
  result.odometry = Stamped(clip, poses);
  result.optimized = Stamped(clip, graph.poses());
  if (method_ == VoMethod::kClSlam) {
    result.generalizer_odometry = Stamped(clip, generalizer_poses);
  }
  // The next deployment starts from the generalizer (cl_slam and
  // generalizer_only) or the carried-over expert (expert_only).
  if (generalizer) {
    weights_ = std::move(generalizer);
  } else if (adapts) {
    weights_ = std::move(expert);
  }
  result.seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  return result;
}

}  // namespace fleetmem::vo
