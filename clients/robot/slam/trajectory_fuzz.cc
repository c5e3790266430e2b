// libFuzzer harness: every reader of the SLAM module on arbitrary bytes —
// trajectory files (both formats and detection), relations files, tables of
// deployments (and their scoring), and scan attachments from peers.
#include <cstddef>
#include <cstdint>
#include <string_view>

#include "clients/robot/slam/scan_matcher.h"
#include "clients/robot/slam/trajectory.h"
#include "clients/robot/slam/trajectory_metrics.h"

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size) {
  namespace slam = fleetmem::slam;
  const std::string_view text(reinterpret_cast<const char*>(data), size);
  slam::DetectTrajectoryFormat(text, "input").IgnoreError();
  for (slam::TrajectoryFormat f :
       {slam::TrajectoryFormat::kKitti, slam::TrajectoryFormat::kTum}) {
    absl::StatusOr<slam::Trajectory> t = slam::ParseTrajectory(text, f, "in");
    if (t.ok() && t->size() >= 3) {
      slam::AbsoluteTrajectoryError(*t, *t, slam::Alignment::kSim3)
          .IgnoreError();
      slam::RelativePoseError(*t, *t, {.delta_m = 1.0}).IgnoreError();
      slam::KittiOdometryError(*t, *t);
    }
  }
  absl::StatusOr<std::vector<slam::Relation>> r =
      slam::ParseRelations(text, "in");
  absl::StatusOr<std::vector<slam::Deployment>> d =
      slam::ParseDeployments(text, "in");
  if (d.ok()) slam::ScoreDeployments(*d).IgnoreError();
  absl::StatusOr<fleetmem::robot::LaserScan> scan = slam::DecodeScan(text);
  if (scan.ok()) slam::ScanPoints(*scan, 30.0);
  return 0;
}
