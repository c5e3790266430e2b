#include "tools/eval/trajectory_eval.h"

#include <cstdio>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/slam/trajectory.h"
#include "clients/robot/slam/trajectory_metrics.h"
#include "google/protobuf/util/json_util.h"
#include "services/common/files.h"
#include "tools/eval/trajectory_report.pb.h"

namespace fleetmem::eval {
namespace {

void Fill(const slam::ErrorStats& s, ErrorStats* out) {
  out->set_count(s.count);
  out->set_rmse(s.rmse);
  out->set_mean(s.mean);
  out->set_median(s.median);
  out->set_std(s.std);
  out->set_min(s.min);
  out->set_max(s.max);
}

absl::Status PrintJson(const google::protobuf::Message& message) {
  std::string json;
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = true;
  options.always_print_primitive_fields = true;
  options.preserve_proto_field_names = true;
  if (!google::protobuf::util::MessageToJsonString(message, &json, options)
           .ok()) {
    return absl::InternalError("cannot print the report as JSON");
  }
  std::fputs(json.c_str(), stdout);
  return absl::OkStatus();
}

void PrintStats(const char* what, const ErrorStats& s) {
  std::printf(
      "%-22s rmse %10.6f  mean %10.6f  median %10.6f  std %10.6f  "
      "min %10.6f  max %10.6f  (n = %llu)\n",
      what, s.rmse(), s.mean(), s.median(), s.std(), s.min(), s.max(),
      static_cast<unsigned long long>(s.count()));
}

}  // namespace

absl::Status RunTrajectoryEval(const TrajectoryEvalOptions& options) {
  std::optional<slam::TrajectoryFormat> format;
  if (!options.format.empty()) {
    absl::StatusOr<slam::TrajectoryFormat> f =
        slam::ParseTrajectoryFormat(options.format);
    if (!f.ok()) return f.status();
    format = *f;
  }
  absl::StatusOr<slam::Alignment> alignment =
      slam::ParseAlignment(options.align);
  if (!alignment.ok()) return alignment.status();
  slam::TrajectoryFormat reference_format = slam::TrajectoryFormat::kTum;
  absl::StatusOr<slam::Trajectory> reference =
      slam::ReadTrajectoryFile(options.reference, format, &reference_format);
  if (!reference.ok()) return reference.status();
  absl::StatusOr<slam::Trajectory> estimate =
      slam::ReadTrajectoryFile(options.estimate, format);
  if (!estimate.ok()) return estimate.status();
  // KITTI files carry no time: pair by index.
  const bool by_index = reference_format == slam::TrajectoryFormat::kKitti;
  absl::StatusOr<std::pair<slam::Trajectory, slam::Trajectory>> pairs =
      slam::AssociatedPoses(*reference, *estimate, by_index,
                            options.max_time_diff_s);
  if (!pairs.ok()) return pairs.status();
  const auto& [ref, est] = *pairs;

  absl::StatusOr<slam::AteResult> ate =
      slam::AbsoluteTrajectoryError(ref, est, *alignment);
  if (!ate.ok()) return ate.status();
  slam::RpeOptions rpe_options;
  rpe_options.delta_m = options.rpe_delta_m;
  rpe_options.delta_frames = options.rpe_delta_frames;
  rpe_options.pairs_from_reference = options.pairs_from_reference;
  absl::StatusOr<slam::RpeResult> rpe =
      slam::RelativePoseError(ref, est, rpe_options);
  if (!rpe.ok()) return rpe.status();
  const slam::KittiOdometryResult kitti = slam::KittiOdometryError(ref, est);

  TrajectoryReport report;
  report.set_reference(options.reference);
  report.set_estimate(options.estimate);
  report.set_format(by_index ? "kitti" : "tum");
  report.set_alignment(options.align);
  report.set_poses(ref.size());
  report.set_ate_rmse_m(ate->translation_m.rmse);
  Fill(ate->translation_m, report.mutable_ate_m());
  report.set_alignment_scale(ate->alignment.scale);
  report.set_rpe_delta(
      absl::StrCat(options.rpe_delta_m > 0
                       ? absl::StrCat(options.rpe_delta_m, " m")
                       : absl::StrCat(options.rpe_delta_frames, " frames"),
                   options.pairs_from_reference ? ", pairs on the reference"
                                                : ", pairs on the estimate"));
  report.set_rpe_trans_rmse_m(rpe->translation_m.rmse);
  Fill(rpe->translation_m, report.mutable_rpe_trans_m());
  Fill(rpe->rotation_deg, report.mutable_rpe_rot_deg());
  report.set_kitti_segments(kitti.segments);
  report.set_kitti_t_err_percent(kitti.t_err_percent);
  report.set_kitti_r_err_deg_per_100m(kitti.r_err_deg_per_100m);
  if (options.json) return PrintJson(report);
  std::printf(
      "reference %s\nestimate  %s\n%llu poses (%s), alignment %s "
      "(scale %.6f)\n",
      options.reference.c_str(), options.estimate.c_str(),
      static_cast<unsigned long long>(report.poses()), report.format().c_str(),
      options.align.c_str(), report.alignment_scale());
  PrintStats("ATE (m)", report.ate_m());
  std::printf("RPE delta %s\n", report.rpe_delta().c_str());
  PrintStats("RPE translation (m)", report.rpe_trans_m());
  PrintStats("RPE rotation (deg)", report.rpe_rot_deg());
  if (kitti.segments > 0) {
    std::printf("KITTI t_err %.4f %%  r_err %.4f deg/100 m  (%llu segments)\n",
                kitti.t_err_percent, kitti.r_err_deg_per_100m,
                static_cast<unsigned long long>(kitti.segments));
  } else {
    std::printf("KITTI t_err/r_err: undefined (path shorter than 100 m)\n");
  }
  return absl::OkStatus();
}

absl::Status RunRelationsEval(const RelationsEvalOptions& options) {
  absl::StatusOr<slam::Trajectory> estimate =
      slam::ReadTrajectoryFile(options.estimate, std::nullopt);
  if (!estimate.ok()) return estimate.status();
  absl::StatusOr<std::string> text = files::ReadFile(options.relations);
  if (!text.ok()) return text.status();
  absl::StatusOr<std::vector<slam::Relation>> relations =
      slam::ParseRelations(*text, options.relations);
  if (!relations.ok()) return relations.status();
  absl::StatusOr<slam::RelationsResult> r =
      slam::RelationsError(*estimate, *relations, options.max_time_diff_s);
  if (!r.ok()) return r.status();
  RelationsReport report;
  report.set_estimate(options.estimate);
  report.set_relations(options.relations);
  report.set_relations_scored(r->translation_m.count);
  report.set_relations_missing(r->missing);
  Fill(r->translation_m, report.mutable_translation_m());
  Fill(r->rotation_deg, report.mutable_rotation_deg());
  report.set_translation_sq_mean(r->translation_sq_mean);
  report.set_translation_sq_std(r->translation_sq_std);
  report.set_rotation_sq_mean(r->rotation_sq_mean);
  report.set_rotation_sq_std(r->rotation_sq_std);
  if (options.json) return PrintJson(report);
  std::printf("estimate  %s\nrelations %s: %llu scored, %llu missing\n",
              options.estimate.c_str(), options.relations.c_str(),
              static_cast<unsigned long long>(report.relations_scored()),
              static_cast<unsigned long long>(report.relations_missing()));
  std::printf("translation: %.4f +- %.4f m    (squared %.4f +- %.4f m^2)\n",
              r->translation_m.mean, r->translation_m.std,
              r->translation_sq_mean, r->translation_sq_std);
  std::printf("rotation:    %.4f +- %.4f deg  (squared %.4f +- %.4f deg^2)\n",
              r->rotation_deg.mean, r->rotation_deg.std, r->rotation_sq_mean,
              r->rotation_sq_std);
  return absl::OkStatus();
}

absl::Status RunContinualScores(const std::string& table, bool json) {
  absl::StatusOr<std::string> text = files::ReadFile(table);
  if (!text.ok()) return text.status();
  absl::StatusOr<std::vector<slam::Deployment>> deployments =
      slam::ParseDeployments(*text, table);
  if (!deployments.ok()) return deployments.status();
  absl::StatusOr<slam::ContinualScores> s =
      slam::ScoreDeployments(*deployments);
  if (!s.ok()) return s.status();
  ContinualReport report;
  report.set_table(table);
  report.set_aq_trans(s->aq_trans);
  report.set_aq_rot(s->aq_rot);
  report.set_rq_trans(s->rq_trans);
  report.set_rq_rot(s->rq_rot);
  report.set_aq_sequences(s->aq_sequences);
  report.set_rq_pairs(s->rq_pairs);
  if (json) return PrintJson(report);
  std::printf("AQ_trans %.4f  AQ_rot %.4f  (%llu sequences)\n", s->aq_trans,
              s->aq_rot, static_cast<unsigned long long>(s->aq_sequences));
  std::printf("RQ_trans %.4f  RQ_rot %.4f  (%llu pairs)\n", s->rq_trans,
              s->rq_rot, static_cast<unsigned long long>(s->rq_pairs));
  return absl::OkStatus();
}

}  // namespace fleetmem::eval
