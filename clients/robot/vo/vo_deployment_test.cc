#include "clients/robot/vo/vo_deployment.h"

#include <filesystem>
#include <string>

#include "services/common/files.h"
#include "gtest/gtest.h"
#include "fleetmem_paths.h"

namespace fleetmem::vo {
namespace {

namespace fs = std::filesystem;

TEST(RunVoDeployment, WritesTrajectoriesAndCarriesTheWeights) {
  const std::string dir = testing::TempDir() + "/vo_deployment";
  fs::remove_all(dir);
  fs::create_directories(dir + "/robot");
  DepthPoseOptions mo;
  mo.image_width = 64;
  mo.image_height = 32;
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> model =
      DepthPoseModel::Create(mo);
  ASSERT_TRUE(model.ok());
  ASSERT_TRUE((*model)->Save(dir + "/pretrained.pt").ok());

  VoDeploymentOptions o;
  o.sequence_dir = std::string(FLEETMEM_DATA_DIR) + "/kitti/clip1";
  o.data_dir = dir + "/robot";
  o.vo.update_steps = 1;
  EXPECT_EQ(RunVoDeployment(o).status().code(), absl::StatusCode::kNotFound);
  o.initial_model = dir + "/pretrained.pt";
  absl::StatusOr<VoDeploymentReport> first = RunVoDeployment(o);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->out_dir, o.data_dir + "/vo/clip1-1");
  EXPECT_EQ(first->result.odometry.size(), 51u);
  EXPECT_GE(first->ate_se3_m, 0.0);
  for (const char* f : {"trajectory.kitti", "trajectory.tum", "odometry.kitti",
                        "odometry.tum", "vo.json"}) {
    EXPECT_TRUE(fs::exists(first->out_dir + "/" + f)) << f;
  }
  ASSERT_TRUE(fs::exists(o.data_dir + "/vo-weights.pt"));
  // The second deployment starts from the robot's own weights.
  absl::StatusOr<VoDeploymentReport> second = RunVoDeployment(o);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_EQ(second->out_dir, o.data_dir + "/vo/clip1-2");
  absl::StatusOr<std::string> json =
      files::ReadFile(second->out_dir + "/vo.json");
  ASSERT_TRUE(json.ok());
  EXPECT_NE(json->find("vo-weights.pt"), std::string::npos) << *json;
  // A missing sequence changes nothing.
  o.sequence_dir = dir + "/missing";
  EXPECT_EQ(RunVoDeployment(o).status().code(), absl::StatusCode::kNotFound);
  EXPECT_FALSE(fs::exists(o.data_dir + "/vo/clip1-3"));
  fs::remove_all(dir);
}

}  // namespace
}  // namespace fleetmem::vo
