#include "tools/eval/continual_vo_eval.h"

#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <map>
#include <memory>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "clients/robot/learning/depth_pose_model.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/slam/trajectory_metrics.h"
#include "clients/robot/vo/classical_vo.h"
#include "clients/robot/vo/continual_vo.h"
#include "services/common/files.h"

namespace fleetmem::eval {
namespace {

using files::WriteFile;

constexpr int kWidth = 192;
constexpr int kHeight = 64;

struct Row {
  std::string order;     // the pre-training clip
  std::string sequence;  // "pre>clip1>clip2"
  std::string scene;     // the clip deployed on
  std::string method;
  size_t frames = 0;
  double ate_se3 = 0.0;
  double ate_sim3 = 0.0;
  double rpe_frame_trans = 0.0;
  double rpe_frame_rot = 0.0;
  double rpe_10m_trans = 0.0;
  double rpe_10m_rot = 0.0;
  slam::KittiOdometryResult short_segments;
  slam::KittiOdometryResult kitti;
  double seconds = 0.0;
  int update_steps = 0;
  size_t replay_samples = 0;
};

absl::StatusOr<Row> Score(const vo::KittiClip& clip,
                          const slam::Trajectory& estimate) {
  Row row;
  row.frames = estimate.size();
  absl::StatusOr<slam::AteResult> se3 = slam::AbsoluteTrajectoryError(
      clip.ground_truth, estimate, slam::Alignment::kSe3);
  if (!se3.ok()) return se3.status();
  absl::StatusOr<slam::AteResult> sim3 = slam::AbsoluteTrajectoryError(
      clip.ground_truth, estimate, slam::Alignment::kSim3);
  if (!sim3.ok()) return sim3.status();
  row.ate_se3 = se3->translation_m.rmse;
  row.ate_sim3 = sim3->translation_m.rmse;
  absl::StatusOr<slam::RpeResult> frame =
      slam::RelativePoseError(clip.ground_truth, estimate, {});
  if (!frame.ok()) return frame.status();
  row.rpe_frame_trans = frame->translation_m.rmse;
  row.rpe_frame_rot = frame->rotation_deg.rmse;
  absl::StatusOr<slam::RpeResult> ten =
      slam::RelativePoseError(clip.ground_truth, estimate, {.delta_m = 10.0});
  if (!ten.ok()) return ten.status();
  row.rpe_10m_trans = ten->translation_m.rmse;
  row.rpe_10m_rot = ten->rotation_deg.rmse;
  row.short_segments = slam::KittiOdometryError(
      clip.ground_truth, estimate,
      {.lengths_m = {10, 20, 30, 40}, .step_frames = 1});
  row.kitti = slam::KittiOdometryError(clip.ground_truth, estimate);
  return row;
}

absl::Status WriteTrajectory(const std::string& stem,
                             const slam::Trajectory& t) {
  if (absl::Status s =
          WriteFile(stem + ".kitti",
                    slam::FormatTrajectory(t, slam::TrajectoryFormat::kKitti));
      !s.ok()) {
    return s;
  }
  return WriteFile(stem + ".tum",
                   slam::FormatTrajectory(t, slam::TrajectoryFormat::kTum));
}

// x (right) and z (forward) of a trajectory, gnuplot data.
std::string PlotData(const slam::Trajectory& t) {
  std::string out;
  for (const slam::StampedPose& p : t) {
    absl::StrAppendFormat(&out, "%.4f %.4f\n", p.pose.translation().x(),
                          p.pose.translation().z());
  }
  return out + "\n\n";
}

// A clip's scene name for AQ/RQ: an environment is a scene name without
// trailing digits, so clip1 and clip2 become clipA and clipB.
std::string SceneName(const std::string& clip) {
  if (clip == "clip1") return "clipA";
  if (clip == "clip2") return "clipB";
  return clip;
}

std::string Progress(const std::string& what, size_t frame, size_t frames) {
  return absl::StrFormat("\r  %-46s frame %2zu/%zu", what, frame + 1, frames);
}

struct Context {
  const ContinualVoEvalOptions* options;
  std::string dir;
  bool tty = false;  // progress redrawn in place on a terminal
  std::vector<Row> rows;
  // Plot blocks per method: (title, data of ground truth, fixed, method).
  std::map<std::string, std::vector<std::pair<std::string, std::string>>> plots;
};

// The model pre-trained on `x` from scratch (no ImageNet weights here) at
// 1e-3, then copied into one at CL-SLAM's adaptation rate, 1e-4, with its
// encoders frozen, and saved in `order_dir`/weights/pretrained.pt.
absl::StatusOr<std::unique_ptr<vo::DepthPoseModel>> Pretrained(
    Context& ctx, const vo::KittiClip& x, int pretrain_steps,
    const std::string& order_dir) {
  const ContinualVoEvalOptions& o = *ctx.options;
  vo::DepthPoseOptions model_options;
  model_options.image_width = kWidth;
  model_options.image_height = kHeight;
  model_options.seed = o.seed;
  model_options.learning_rate = 1e-3;
  absl::StatusOr<std::unique_ptr<vo::DepthPoseModel>> model =
      vo::DepthPoseModel::Create(model_options);
  if (!model.ok()) return model.status();
  std::fprintf(stderr,
               "pre-training on %s: %d steps of 4 triplets, stereo + "
               "monocular, %dx%d, %lld parameters\n",
               x.name.c_str(), pretrain_steps, kWidth, kHeight,
               static_cast<long long>((*model)->ParameterCount()));
  const auto start = std::chrono::steady_clock::now();
  absl::StatusOr<vo::VoLosses> pre = vo::Pretrain(
      **model, x, {.steps = pretrain_steps, .batch_size = 4, .seed = o.seed},
      [&](int step, const vo::VoLosses& l) {
        if ((ctx.tty && step % 25 == 0) || (step + 1) % 500 == 0 ||
            step + 1 == pretrain_steps) {
          std::fprintf(stderr,
                       "%s  step %4d/%d  loss %.4f (photometric %.4f, "
                       "velocity %.3f m)",
                       ctx.tty ? "\r" : "\n", step + 1, pretrain_steps, l.total,
                       l.photometric, l.velocity);
        }
      });
  if (!pre.ok()) return pre.status();
  std::fprintf(
      stderr, "\n  pre-trained in %.0f s\n",
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count());
  vo::DepthPoseOptions adapt_options = model_options;
  adapt_options.learning_rate = 1e-4;
  absl::StatusOr<std::unique_ptr<vo::DepthPoseModel>> pretrained =
      vo::DepthPoseModel::Create(adapt_options);
  if (!pretrained.ok()) return pretrained.status();
  (*pretrained)->FreezeEncoders();
  if (absl::Status s = (*pretrained)->CopyWeightsFrom(**model); !s.ok()) {
    return s;
  }
  if (absl::Status s =
          (*pretrained)->Save(order_dir + "/weights/pretrained.pt");
      !s.ok()) {
    return s;
  }
  return pretrained;
}

// One deployment of a method's model on a clip, named by the sequence of
// clips it saw: its row, trajectory, weights and plot block.
struct Step {
  vo::ContinualVo* vo;
  const vo::KittiClip* clip;
  std::string sequence;
};
absl::Status Deploy(Context& ctx, const Step& step, const std::string& name,
                    const std::string& order, const std::string& order_dir) {
  const std::string what = absl::StrCat(name, " ", step.sequence);
  absl::StatusOr<vo::DeploymentResult> d = step.vo->Deploy(
      step.clip->name, *step.clip, [&](size_t frame, size_t frames) {
        if (ctx.tty || frame + 1 == frames) {
          std::fprintf(stderr, "%s", Progress(what, frame, frames).c_str());
        }
      });
  if (!d.ok()) return d.status();
  absl::StatusOr<Row> row = Score(*step.clip, d->odometry);
  if (!row.ok()) return row.status();
  row->order = order;
  row->sequence = step.sequence;
  row->scene = step.clip->name;
  row->method = name;
  row->seconds = d->seconds;
  row->update_steps = d->update_steps;
  for (const auto& [env, buffer] : step.vo->replay().buffers()) {
    row->replay_samples += buffer.size();
  }
  std::fprintf(stderr, "  ATE %.2f m (SE(3)), %.0f s\n", row->ate_se3,
               d->seconds);
  std::string stem = step.sequence;
  std::replace(stem.begin(), stem.end(), '>', '_');
  if (absl::Status s = WriteTrajectory(
          absl::StrCat(order_dir, "/", stem, "_", name), d->odometry);
      !s.ok()) {
    return s;
  }
  if (absl::Status s = step.vo->weights().Save(
          absl::StrCat(order_dir, "/weights/", stem, "_", name, ".pt"));
      !s.ok()) {
    return s;
  }
  ctx.plots[name].push_back(
      {absl::StrCat(step.sequence, " (on ", step.clip->name, ")"),
       PlotData(step.clip->ground_truth) + PlotData(d->odometry)});
  ctx.rows.push_back(*row);
  return absl::OkStatus();
}

absl::Status RunOrder(Context& ctx, const vo::KittiClip& x,
                      const vo::KittiClip& y, int pretrain_steps) {
  const ContinualVoEvalOptions& o = *ctx.options;
  const std::string order_dir = absl::StrCat(ctx.dir, "/", x.name, "_first");
  std::filesystem::create_directories(order_dir + "/weights");
  absl::StatusOr<std::unique_ptr<vo::DepthPoseModel>> pretrained =
      Pretrained(ctx, x, pretrain_steps, order_dir);
  if (!pretrained.ok()) return pretrained.status();
  vo::ContinualVoOptions vo_options;
  vo_options.update_steps = o.update_steps;
  vo_options.seed = o.seed;
  const std::string pre_x = "pre>" + x.name;
  for (vo::VoMethod method :
       {vo::VoMethod::kFixed, vo::VoMethod::kExpertOnly,
        vo::VoMethod::kGeneralizerOnly, vo::VoMethod::kClSlam}) {
    const std::string name = vo::VoMethodName(method);
    absl::StatusOr<std::unique_ptr<vo::ContinualVo>> run =
        vo::ContinualVo::Create(**pretrained, method, vo_options);
    if (!run.ok()) return run.status();
    if (method == vo::VoMethod::kGeneralizerOnly ||
        method == vo::VoMethod::kClSlam) {
      if (absl::Status s = (*run)->Remember(x.name, x); !s.ok()) return s;
    }
    absl::StatusOr<std::unique_ptr<vo::ContinualVo>> branch = (*run)->Clone();
    if (!branch.ok()) return branch.status();
    for (const Step& step :
         {Step{run->get(), &y, pre_x + ">" + y.name},
          Step{run->get(), &x, pre_x + ">" + y.name + ">" + x.name},
          Step{branch->get(), &x, pre_x + ">" + x.name}}) {
      if (absl::Status s = Deploy(ctx, step, name, x.name, order_dir);
          !s.ok()) {
        return s;
      }
    }
  }
  return absl::OkStatus();
}

absl::Status RunClassical(Context& ctx, const vo::KittiClip& clip) {
  absl::StatusOr<vo::ClassicalVoResult> r = vo::RunClassicalVo(clip);
  if (!r.ok()) return r.status();
  absl::StatusOr<Row> row = Score(clip, r->odometry);
  if (!row.ok()) return row.status();
  row->order = "-";
  row->sequence = clip.name;
  row->scene = clip.name;
  row->method = "classical";
  ctx.rows.push_back(*row);
  ctx.plots["classical"].push_back(
      {absl::StrCat("on ", clip.name),
       PlotData(clip.ground_truth) + PlotData(r->odometry)});
  return WriteTrajectory(absl::StrCat(ctx.dir, "/", clip.name, "_classical"),
                         r->odometry);
}

absl::Status WritePlots(const Context& ctx) {
  for (const auto& [method, panels] : ctx.plots) {
    std::string data,
        script = absl::StrFormat(
            "set terminal pngcairo size %d,430 font 'sans,9'\n"
            "set output '%s/plot_%s.png'\n"
            "set termoption noenhanced\n"
            "set multiplot layout 1,%d title '%s: trajectories (x right, z "
            "forward, m) against KITTI ground truth'\n"
            "set size ratio -1; set grid; set key bottom right font ',8'\n",
            360 * int(panels.size()), ctx.dir, method, int(panels.size()),
            method);
    for (size_t i = 0; i < panels.size(); ++i) {
      data += panels[i].second;
      absl::StrAppendFormat(
          &script,
          "set title '%s'\n"
          "plot '%s/plot_%s.dat' index %d using 1:2 with lines lw 2 lc "
          "rgb 'black' title 'ground truth', '' index %d using 1:2 with "
          "linespoints pt 7 ps 0.4 lc rgb '#d62728' title '%s'\n",
          panels[i].first, ctx.dir, method, int(2 * i), int(2 * i + 1), method);
    }
    script += "unset multiplot\n";
    if (absl::Status s =
            WriteFile(absl::StrCat(ctx.dir, "/plot_", method, ".dat"), data);
        !s.ok()) {
      return s;
    }
    const std::string gp = absl::StrCat(ctx.dir, "/plot_", method, ".gp");
    if (absl::Status s = WriteFile(gp, script); !s.ok()) return s;
    const std::string command =
        absl::StrCat("gnuplot '", gp, "' 2>>'", ctx.dir, "/gnuplot.log'");
    if (std::system(command.c_str()) != 0) {
      return absl::InternalError(absl::StrCat("gnuplot failed to draw plot_",
                                              method, ".png; see ", ctx.dir,
                                              "/gnuplot.log"));
    }
  }
  return absl::OkStatus();
}

}  // namespace

namespace {

// The two KITTI clips (each cut to options.frames, if set).
absl::StatusOr<std::vector<vo::KittiClip>> LoadClips(
    const ContinualVoEvalOptions& options) {
  std::vector<vo::KittiClip> clips;
  for (const char* name : {"clip1", "clip2"}) {
    absl::StatusOr<vo::KittiClip> clip = vo::LoadKittiClip(
        absl::StrCat(options.data_root, "/kitti/", name), kWidth, kHeight);
    if (!clip.ok()) return clip.status();
    if (options.frames > 0 && clip->left.size() > size_t(options.frames)) {
      clips.push_back(vo::SubClip(*clip, 0, options.frames));
    } else {
      clips.push_back(*std::move(clip));
    }
  }
  return clips;
}

// summary.csv: a row per deployment.
std::string SummaryCsv(const std::vector<Row>& rows) {
  std::string summary =
      "order,sequence,scene,method,frames,ate_se3_m,ate_sim3_m,"
      "rpe_frame_trans_m,rpe_frame_rot_deg,rpe_10m_trans_m,rpe_10m_rot_deg,"
      "t_err_10_40m_pct,r_err_10_40m_deg_per_100m,kitti_t_err_pct,"
      "kitti_r_err_deg_per_100m,update_steps,replay_samples,seconds\n";
  for (const Row& r : rows) {
    const std::string kitti_t =
        r.kitti.segments > 0 ? absl::StrFormat("%.4f", r.kitti.t_err_percent)
                             : "n/a";
    const std::string kitti_r =
        r.kitti.segments > 0
            ? absl::StrFormat("%.4f", r.kitti.r_err_deg_per_100m)
            : "n/a";
    absl::StrAppendFormat(
        &summary,
        "%s,%s,%s,%s,%zu,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%.4f,%s,%s,%d,%zu,%"
        ".1f\n",
        r.order, r.sequence, r.scene, r.method, r.frames, r.ate_se3, r.ate_sim3,
        r.rpe_frame_trans, r.rpe_frame_rot, r.rpe_10m_trans, r.rpe_10m_rot,
        r.short_segments.t_err_percent, r.short_segments.r_err_deg_per_100m,
        kitti_t, kitti_r, r.update_steps, r.replay_samples, r.seconds);
  }
  return summary;
}

// The results: summary.csv, deployments.csv, continual.csv (AQ and RQ per
// method), summary.txt (also on stdout) and the plots.
absl::Status WriteResults(Context& ctx,
                          std::chrono::steady_clock::time_point start) {
  const ContinualVoEvalOptions& options = *ctx.options;
  const std::string summary = SummaryCsv(ctx.rows);
  std::string deployments = "method,sequence,t_err,r_err\n";
  // AQ and RQ per method (fleetmem-eval continual's computation).
  std::map<std::string, std::vector<slam::Deployment>> by_method;
  for (const Row& r : ctx.rows) {
    if (r.method == "classical") continue;
    slam::Deployment d;
    for (absl::string_view s : absl::StrSplit(r.sequence, '>')) {
      d.scenes.push_back(SceneName(std::string(s)));
    }
    d.t_err_percent = r.short_segments.t_err_percent;
    d.r_err_deg_per_100m = r.short_segments.r_err_deg_per_100m;
    by_method[r.method].push_back(d);
    absl::StrAppendFormat(&deployments, "%s,%s,%.4f,%.4f\n", r.method,
                          absl::StrJoin(d.scenes, ">"), d.t_err_percent,
                          d.r_err_deg_per_100m);
  }
  std::string continual =
      "method,aq_trans,aq_rot,rq_trans,rq_rot,aq_sequences,rq_pairs\n";
  std::string table = absl::StrFormat(
      "\n%-17s %-24s %8s %8s %9s %9s %8s\n", "method", "sequence", "ATE se3",
      "ATE sim3", "RPE/frm", "t_err10-40", "r_err");
  for (const Row& r : ctx.rows) {
    absl::StrAppendFormat(&table, "%-17s %-24s %8.3f %8.3f %9.3f %9.2f %8.2f\n",
                          r.method, r.sequence, r.ate_se3, r.ate_sim3,
                          r.rpe_frame_trans, r.short_segments.t_err_percent,
                          r.short_segments.r_err_deg_per_100m);
  }
  absl::StrAppendFormat(&table, "\n%-17s %9s %9s %10s %10s\n", "method",
                        "AQ_trans", "AQ_rot", "RQ_trans", "RQ_rot");
  for (const auto& [method, ds] : by_method) {
    absl::StatusOr<slam::ContinualScores> s = slam::ScoreDeployments(ds);
    if (!s.ok()) return s.status();
    absl::StrAppendFormat(&continual, "%s,%.4f,%.4f,%.5f,%.5f,%zu,%zu\n",
                          method, s->aq_trans, s->aq_rot, s->rq_trans,
                          s->rq_rot, s->aq_sequences, s->rq_pairs);
    absl::StrAppendFormat(&table, "%-17s %9.4f %9.4f %10.5f %10.5f\n", method,
                          s->aq_trans, s->aq_rot, s->rq_trans, s->rq_rot);
  }
  for (const auto& [name, text] :
       std::vector<std::pair<std::string, std::string>>{
           {"summary.csv", summary},
           {"deployments.csv", deployments},
           {"continual.csv", continual},
           {"summary.txt", table}}) {
    if (absl::Status s = WriteFile(options.out_dir + "/" + name, text);
        !s.ok()) {
      return s;
    }
  }
  if (absl::Status s = WritePlots(ctx); !s.ok()) return s;
  std::printf(
      "%s\nwall time %.0f s; results in %s\n", table.c_str(),
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count(),
      options.out_dir.c_str());
  return absl::OkStatus();
}

}  // namespace

absl::Status RunContinualVoEval(const ContinualVoEvalOptions& options) {
  if (options.update_steps < 0 || options.pretrain_steps < 0) {
    return absl::InvalidArgumentError("step counts must be >= 0");
  }
  if (options.frames != 0 && options.frames < 3) {
    return absl::InvalidArgumentError("--frames: 0 (all) or at least 3");
  }
  robot::gpl::SetTorchThreads(options.threads);
  std::error_code ec;
  std::filesystem::create_directories(options.out_dir, ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("cannot create ", options.out_dir, ": ", ec.message()));
  }
  absl::StatusOr<std::vector<vo::KittiClip>> clips = LoadClips(options);
  if (!clips.ok()) return clips.status();
  const int pretrain_steps = options.pretrain_steps > 0 ? options.pretrain_steps
                             : options.quick            ? 1500
                                                        : 4000;
  Context ctx{&options, options.out_dir, isatty(2) != 0, {}, {}};
  const auto start = std::chrono::steady_clock::now();
  for (const vo::KittiClip& clip : *clips) {
    if (absl::Status s = RunClassical(ctx, clip); !s.ok()) return s;
  }
  if (absl::Status s = RunOrder(ctx, (*clips)[0], (*clips)[1], pretrain_steps);
      !s.ok()) {
    return s;
  }
  if (!options.quick) {
    if (absl::Status s =
            RunOrder(ctx, (*clips)[1], (*clips)[0], pretrain_steps);
        !s.ok()) {
      return s;
    }
  }
  return WriteResults(ctx, start);
}

}  // namespace fleetmem::eval
