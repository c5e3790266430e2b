#include "clients/robot/vo/continual_vo.h"

#include <string>

#include "gtest/gtest.h"
#include "fleetmem_paths.h"

namespace fleetmem::vo {
namespace {

constexpr int kW = 64, kH = 32;

KittiClip Clip(size_t frames) {
  absl::StatusOr<KittiClip> clip =
      LoadKittiClip(std::string(FLEETMEM_DATA_DIR) + "/kitti/clip1", kW, kH);
  EXPECT_TRUE(clip.ok()) << clip.status();
  return clip.ok() ? SubClip(*clip, 0, frames) : KittiClip{};
}

std::unique_ptr<DepthPoseModel> Model() {
  DepthPoseOptions o;
  o.image_width = kW;
  o.image_height = kH;
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> m = DepthPoseModel::Create(o);
  EXPECT_TRUE(m.ok());
  return m.ok() ? std::move(*m) : nullptr;
}

ContinualVoOptions Options() {
  ContinualVoOptions o;
  o.update_steps = 2;
  return o;
}

double Difference(DepthPoseModel& a, DepthPoseModel& b, const KittiClip& c) {
  absl::StatusOr<Eigen::Isometry3d> x = a.PredictMotion(c.left[0], c.left[1]);
  absl::StatusOr<Eigen::Isometry3d> y = b.PredictMotion(c.left[0], c.left[1]);
  EXPECT_TRUE(x.ok() && y.ok());
  return (x->matrix() - y->matrix()).norm();
}

TEST(ContinualVo, FixedChainsTheNetworksMotionsAndLearnsNothing) {
  const KittiClip clip = Clip(5);
  std::unique_ptr<DepthPoseModel> model = Model();
  absl::StatusOr<std::unique_ptr<ContinualVo>> vo =
      ContinualVo::Create(*model, VoMethod::kFixed, Options());
  ASSERT_TRUE(vo.ok()) << vo.status();
  absl::StatusOr<DeploymentResult> r = (*vo)->Deploy("a", clip);
  ASSERT_TRUE(r.ok()) << r.status();
  ASSERT_EQ(r->odometry.size(), 5u);
  EXPECT_EQ(r->update_steps, 0);
  // Pose composition: pose_i = pose_{i-1} * T_{i-1,i}, T_{a,b} the pose of
  // b's camera in a's frame.
  Eigen::Isometry3d chained = Eigen::Isometry3d::Identity();
  for (size_t i = 1; i < 5; ++i) {
    absl::StatusOr<Eigen::Isometry3d> m =
        model->PredictMotion(clip.left[i - 1], clip.left[i]);
    ASSERT_TRUE(m.ok());
    chained = chained * *m;
    EXPECT_LT((r->odometry[i].pose.matrix() - chained.matrix()).norm(), 1e-9);
    EXPECT_DOUBLE_EQ(r->odometry[i].time_s, clip.ground_truth[i].time_s);
  }
  EXPECT_LT(
      Difference(*model, const_cast<DepthPoseModel&>((*vo)->weights()), clip),
      1e-12);
}

TEST(ContinualVo, ClSlamAdaptsBothAndKeepsTheGeneralizer) {
  const KittiClip clip = Clip(6);
  std::unique_ptr<DepthPoseModel> model = Model();
  absl::StatusOr<std::unique_ptr<ContinualVo>> vo =
      ContinualVo::Create(*model, VoMethod::kClSlam, Options());
  ASSERT_TRUE(vo.ok());
  ASSERT_TRUE((*vo)->Remember("pre", Clip(4)).ok());
  ASSERT_EQ((*vo)->replay().buffers().count("pre"), 1u);
  absl::StatusOr<std::unique_ptr<ContinualVo>> branch = (*vo)->Clone();
  ASSERT_TRUE(branch.ok());
  absl::StatusOr<DeploymentResult> r = (*vo)->Deploy("a", clip);
  ASSERT_TRUE(r.ok()) << r.status();
  // Frames 2..5 complete a triplet: 4 adapted frames, 2 steps each.
  EXPECT_EQ(r->adapted_frames, 4);
  EXPECT_EQ(r->update_steps, 8);
  EXPECT_EQ(r->skipped_frames, 0);
  EXPECT_EQ(r->generalizer_odometry.size(), 6u);
  EXPECT_GE((*vo)->replay().buffers().at("a").size(), 1u);
  EXPECT_GT(
      Difference(*model, const_cast<DepthPoseModel&>((*vo)->weights()), clip),
      1e-6);
  // The clone branched before the deployment and is untouched by it.
  EXPECT_EQ((*branch)->replay().buffers().count("a"), 0u);
  EXPECT_LT(Difference(*model,
                       const_cast<DepthPoseModel&>((*branch)->weights()), clip),
            1e-12);
}

// CL-SLAM Sec. 5: on the first deployment after pre-training the expert
// alone and CL-SLAM's expert are the same network on the same data; each
// model's own random draws keep the generalizer from changing that.
TEST(ContinualVo, FirstDeploymentExpertEqualsClSlamsExpert) {
  const KittiClip clip = Clip(5);
  std::unique_ptr<DepthPoseModel> model = Model();
  absl::StatusOr<std::unique_ptr<ContinualVo>> expert =
      ContinualVo::Create(*model, VoMethod::kExpertOnly, Options());
  absl::StatusOr<std::unique_ptr<ContinualVo>> both =
      ContinualVo::Create(*model, VoMethod::kClSlam, Options());
  ASSERT_TRUE(expert.ok() && both.ok());
  ASSERT_TRUE((*both)->Remember("pre", Clip(4)).ok());
  absl::StatusOr<DeploymentResult> a = (*expert)->Deploy("a", clip);
  absl::StatusOr<DeploymentResult> b = (*both)->Deploy("a", clip);
  ASSERT_TRUE(a.ok() && b.ok());
  for (size_t i = 0; i < clip.left.size(); ++i) {
    EXPECT_LT(
        (a->odometry[i].pose.matrix() - b->odometry[i].pose.matrix()).norm(),
        1e-9)
        << i;
  }
}

TEST(ContinualVo, ExpertOnlyKeepsNoReplay) {
  std::unique_ptr<DepthPoseModel> model = Model();
  absl::StatusOr<std::unique_ptr<ContinualVo>> vo =
      ContinualVo::Create(*model, VoMethod::kExpertOnly, Options());
  ASSERT_TRUE(vo.ok());
  absl::StatusOr<DeploymentResult> r = (*vo)->Deploy("a", Clip(4));
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->adapted_frames, 2);
  EXPECT_TRUE((*vo)->replay().buffers().empty());
  EXPECT_TRUE(r->generalizer_odometry.empty());
}

TEST(ContinualVo, SkipsFramesThatBarelyMoved) {
  KittiClip clip = Clip(6);
  clip.travelled_m[2] = 0.05;  // frame 2 is 5 cm from frame 1
  std::unique_ptr<DepthPoseModel> model = Model();
  absl::StatusOr<std::unique_ptr<ContinualVo>> vo =
      ContinualVo::Create(*model, VoMethod::kExpertOnly, Options());
  ASSERT_TRUE(vo.ok());
  absl::StatusOr<DeploymentResult> r = (*vo)->Deploy("a", clip);
  ASSERT_TRUE(r.ok());
  EXPECT_EQ(r->skipped_frames, 1);
  // Accepted: 0, 1, 3, 4, 5 -> triplets end at 3, 4, 5.
  EXPECT_EQ(r->adapted_frames, 3);
  EXPECT_EQ(r->odometry.size(), 6u);
}

TEST(ContinualVo, LoopCandidatesEnterThePoseGraph) {
  ContinualVoOptions o = Options();
  o.update_steps = 0;
  o.loop_similarity = -2.0;  // every pair far enough apart is a candidate
  o.loop_min_gap_frames = 3;
  std::unique_ptr<DepthPoseModel> model = Model();
  absl::StatusOr<std::unique_ptr<ContinualVo>> vo =
      ContinualVo::Create(*model, VoMethod::kFixed, o);
  ASSERT_TRUE(vo.ok());
  absl::StatusOr<DeploymentResult> r = (*vo)->Deploy("a", Clip(5));
  ASSERT_TRUE(r.ok()) << r.status();
  // Frame 3 closes with 0; frame 4 with 0 and 1.
  EXPECT_EQ(r->loops, 3);
  EXPECT_EQ(r->optimized.size(), 5u);
}

TEST(ParseVoMethod, Names) {
  for (VoMethod m : {VoMethod::kFixed, VoMethod::kExpertOnly,
                     VoMethod::kGeneralizerOnly, VoMethod::kClSlam}) {
    EXPECT_EQ(*ParseVoMethod(VoMethodName(m)), m);
  }
  EXPECT_FALSE(ParseVoMethod("both").ok());
}

}  // namespace
}  // namespace fleetmem::vo
