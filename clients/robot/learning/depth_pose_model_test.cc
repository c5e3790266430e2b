#include "clients/robot/learning/depth_pose_model.h"

#include <cmath>
#include <cstdio>
#include <fstream>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "opencv2/imgproc.hpp"

namespace fleetmem::vo {
namespace {

constexpr int kW = 64, kH = 32;

Camera TestCamera() {
  Camera c;
  c.fx = c.fy = 100.0;
  c.cx = 31.5;
  c.cy = 15.5;
  c.width = kW;
  c.height = kH;
  c.baseline_m = 0.5;
  return c;
}

// A smooth random texture f(u, v) on a grid wider than the image by
// `extra` columns; columns 0..3 are flat so that the border clamp of a
// warp samples the same values.
cv::Mat Texture(int extra, uint64_t seed) {
  cv::RNG rng(seed);
  cv::Mat noise(kH, kW + extra, CV_32F);
  rng.fill(noise, cv::RNG::UNIFORM, 0.0, 255.0);
  cv::GaussianBlur(noise, noise, cv::Size(5, 5), 1.2);
  for (int r = 0; r < kH; ++r) {
    for (int c = 0; c < 4; ++c) noise.at<float>(r, c) = noise.at<float>(r, 4);
  }
  return noise;
}

cv::Mat ConstantDepth(float z) {
  return cv::Mat(kH, kW, CV_32F, cv::Scalar(z));
}

Eigen::Isometry3d Translation(double x, double y, double z) {
  Eigen::Isometry3d t = Eigen::Isometry3d::Identity();
  t.translation() = Eigen::Vector3d(x, y, z);
  return t;
}

TEST(PoseFromParameters, MatchesEigenAngleAxis) {
  const Eigen::Vector3d axis = Eigen::Vector3d(0.3, -0.5, 0.8).normalized();
  const double angle = 0.4;
  const Eigen::Vector3d aa = axis * angle;
  const Eigen::Isometry3d pose = PoseFromParameters(
      {float(aa.x()), float(aa.y()), float(aa.z()), 1.5f, -0.25f, 2.0f});
  const Eigen::Matrix3d expected = Eigen::AngleAxisd(angle, axis).matrix();
  EXPECT_LT((pose.linear() - expected).norm(), 1e-5);
  EXPECT_LT((pose.translation() - Eigen::Vector3d(1.5, -0.25, 2.0)).norm(),
            1e-6);
  // Opposite axis-angles compose to the identity rotation.
  const Eigen::Isometry3d back = PoseFromParameters(
      {float(-aa.x()), float(-aa.y()), float(-aa.z()), 0.0f, 0.0f, 0.0f});
  EXPECT_LT(((pose * back).linear() - Eigen::Matrix3d::Identity()).norm(),
            1e-5);
  const Eigen::Isometry3d zero = PoseFromParameters({0, 0, 0, 0, 0, 0});
  EXPECT_LT((zero.matrix() - Eigen::Matrix4d::Identity()).norm(), 1e-6);
}

// A source camera 0.2 m to the right of the target, a wall 10 m away: every
// pixel moves 100 * 0.2 / 10 = 2 px. The source is the target's texture
// shifted by 2 px; warping it back gives the target exactly.
TEST(WarpToTarget, KnownShiftReproducesTheTarget) {
  const cv::Mat f = Texture(2, 7);
  const cv::Mat target = f(cv::Rect(0, 0, kW, kH)).clone();
  const cv::Mat source = f(cv::Rect(2, 0, kW, kH)).clone();
  // X_source = X_target - (0.2, 0, 0): u_source = u_target - 2, and
  // source(u - 2) = f(u) = target(u). So the source sits 0.2 m to the left.
  absl::StatusOr<cv::Mat> warped = WarpToTarget(
      source, ConstantDepth(10.0f), Translation(0.2, 0, 0), TestCamera());
  ASSERT_TRUE(warped.ok()) << warped.status();
  double worst = 0.0;
  for (int r = 0; r < kH; ++r) {
    for (int c = 0; c < kW; ++c) {
      worst = std::max(worst, double(std::abs(warped->at<float>(r, c) -
                                              target.at<float>(r, c))));
    }
  }
  EXPECT_LT(worst, 0.05);
}

TEST(ReprojectionLoss, KnownShiftGivesZeroLossAndAWrongPoseDoesNot) {
  const cv::Mat f = Texture(2, 11);
  const cv::Mat target = f(cv::Rect(0, 0, kW, kH)).clone();
  const std::vector<cv::Mat> sources = {f(cv::Rect(2, 0, kW, kH)).clone()};
  const std::vector<Eigen::Isometry3d> right = {Translation(0.2, 0, 0)};
  const std::vector<Eigen::Isometry3d> wrong = {Translation(-0.3, 0, 0)};
  absl::StatusOr<float> exact =
      ReprojectionLoss(target, sources, ConstantDepth(10.0f), right,
                       TestCamera(), /*automask=*/false);
  ASSERT_TRUE(exact.ok()) << exact.status();
  EXPECT_LT(*exact, 1e-4f);
  absl::StatusOr<float> off =
      ReprojectionLoss(target, sources, ConstantDepth(10.0f), wrong,
                       TestCamera(), /*automask=*/false);
  ASSERT_TRUE(off.ok());
  EXPECT_GT(*off, 0.02f);
  // The wrong depth is as bad as the wrong pose.
  absl::StatusOr<float> bad_depth =
      ReprojectionLoss(target, sources, ConstantDepth(2.0f), right,
                       TestCamera(), /*automask=*/false);
  ASSERT_TRUE(bad_depth.ok());
  EXPECT_GT(*bad_depth, 0.02f);
}

TEST(ReprojectionLoss, MinimumOverSourcesAndAutoMask) {
  const cv::Mat f = Texture(2, 13);
  const cv::Mat target = f(cv::Rect(0, 0, kW, kH)).clone();
  const cv::Mat shifted = f(cv::Rect(2, 0, kW, kH)).clone();
  cv::Mat unrelated = Texture(0, 99);
  // The per-pixel minimum ignores a source that cannot explain the target.
  const std::vector<cv::Mat> two = {shifted, unrelated};
  const std::vector<Eigen::Isometry3d> poses = {Translation(0.2, 0, 0),
                                                Translation(0.2, 0, 0)};
  absl::StatusOr<float> loss = ReprojectionLoss(
      target, two, ConstantDepth(10.0f), poses, TestCamera(), false);
  ASSERT_TRUE(loss.ok());
  EXPECT_LT(*loss, 1e-4f);
  // A static camera (source == target) with a wrong motion: auto-masking
  // keeps the unwarped error, which is zero.
  const std::vector<cv::Mat> same = {target};
  const std::vector<Eigen::Isometry3d> moved = {Translation(0.5, 0, 0)};
  absl::StatusOr<float> unmasked = ReprojectionLoss(
      target, same, ConstantDepth(10.0f), moved, TestCamera(), false);
  absl::StatusOr<float> masked = ReprojectionLoss(
      target, same, ConstantDepth(10.0f), moved, TestCamera(), true);
  ASSERT_TRUE(unmasked.ok() && masked.ok());
  EXPECT_GT(*unmasked, 0.02f);
  EXPECT_LT(*masked, 1e-3f);
}

TEST(ReprojectionLoss, RejectsMismatchedInputs) {
  const cv::Mat target = Texture(0, 1);
  const std::vector<cv::Mat> sources = {target};
  EXPECT_EQ(ReprojectionLoss(target, sources, ConstantDepth(1.0f), {},
                             TestCamera(), true)
                .status()
                .code(),
            absl::StatusCode::kInvalidArgument);
}

std::unique_ptr<DepthPoseModel> SmallModel(uint64_t seed = 1,
                                           float velocity_weight = 0.05f) {
  DepthPoseOptions o;
  o.velocity_weight = velocity_weight;
  o.image_width = kW;
  o.image_height = kH;
  o.learning_rate = 1e-3;
  o.seed = seed;
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> m = DepthPoseModel::Create(o);
  EXPECT_TRUE(m.ok()) << m.status();
  return m.ok() ? std::move(*m) : nullptr;
}

// Three frames of a camera moving 0.2 m to the right past a wall.
Triplet ShiftTriplet() {
  const cv::Mat f = Texture(4, 21);
  Triplet t;
  for (int i = 0; i < 3; ++i) {
    cv::Mat image;
    f(cv::Rect(2 * i, 0, kW, kH)).convertTo(image, CV_8U);
    t.images[i] = image;
  }
  t.distances_m = {0.2, 0.2};
  t.camera = TestCamera();
  return t;
}

TEST(DepthPoseModel, RejectsBadOptionsAndInputs) {
  DepthPoseOptions o;
  o.image_width = 100;
  EXPECT_EQ(DepthPoseModel::Create(o).status().code(),
            absl::StatusCode::kInvalidArgument);
  std::unique_ptr<DepthPoseModel> model = SmallModel();
  ASSERT_NE(model, nullptr);
  EXPECT_EQ(model->TrainStep({}).status().code(),
            absl::StatusCode::kInvalidArgument);
  Triplet t = ShiftTriplet();
  t.camera.fx = 0.0;
  EXPECT_EQ(model->TrainStep({&t, 1}).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(model->PredictMotion(cv::Mat(), t.images[0]).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// With the velocity term weighted up (at 0.05 a random network's near
// depth first makes the photometric term shrink the motion; stereo
// pre-training settles that on real data), the translation's length moves
// to the travelled distance.
TEST(DepthPoseModel, TrainingLowersTheLossAndLearnsTheSpeed) {
  std::unique_ptr<DepthPoseModel> model = SmallModel(1, 1.0f);
  ASSERT_NE(model, nullptr);
  EXPECT_GT(model->ParameterCount(), 100000);
  const Triplet t = ShiftTriplet();
  absl::StatusOr<VoLosses> before = model->Evaluate({&t, 1});
  ASSERT_TRUE(before.ok()) << before.status();
  absl::StatusOr<Eigen::Isometry3d> initial =
      model->PredictMotion(t.images[0], t.images[1]);
  ASSERT_TRUE(initial.ok());
  for (int i = 0; i < 100; ++i) ASSERT_TRUE(model->TrainStep({&t, 1}).ok());
  absl::StatusOr<VoLosses> after = model->Evaluate({&t, 1});
  ASSERT_TRUE(after.ok());
  EXPECT_LT(after->total, before->total);
  EXPECT_LT(after->velocity, before->velocity);
  absl::StatusOr<Eigen::Isometry3d> motion =
      model->PredictMotion(t.images[0], t.images[1]);
  ASSERT_TRUE(motion.ok());
  // The velocity term pulls the translation's length towards 0.2 m.
  EXPECT_LT(std::abs(motion->translation().norm() - 0.2),
            0.5 * std::abs(initial->translation().norm() - 0.2));
}

TEST(DepthPoseModel, FrozenEncodersKeepTheFeature) {
  std::unique_ptr<DepthPoseModel> model = SmallModel();
  ASSERT_NE(model, nullptr);
  model->FreezeEncoders();
  const Triplet t = ShiftTriplet();
  absl::StatusOr<std::vector<float>> f0 = model->Feature(t.images[1]);
  absl::StatusOr<Eigen::Isometry3d> m0 =
      model->PredictMotion(t.images[0], t.images[1]);
  for (int i = 0; i < 5; ++i) ASSERT_TRUE(model->TrainStep({&t, 1}).ok());
  absl::StatusOr<std::vector<float>> f1 = model->Feature(t.images[1]);
  absl::StatusOr<Eigen::Isometry3d> m1 =
      model->PredictMotion(t.images[0], t.images[1]);
  ASSERT_TRUE(f0.ok() && f1.ok() && m0.ok() && m1.ok());
  EXPECT_EQ(*f0, *f1);
  EXPECT_GT((m0->matrix() - m1->matrix()).norm(), 1e-6);
}

TEST(DepthPoseModel, SaveLoadAndCopyKeepTheWeights) {
  std::unique_ptr<DepthPoseModel> model = SmallModel();
  ASSERT_NE(model, nullptr);
  const Triplet t = ShiftTriplet();
  for (int i = 0; i < 3; ++i) ASSERT_TRUE(model->TrainStep({&t, 1}).ok());
  model->FreezeEncoders();
  const std::string path = testing::TempDir() + "/vo_model.pt";
  ASSERT_TRUE(model->Save(path).ok());
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> loaded =
      DepthPoseModel::Load(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_TRUE((*loaded)->encoders_frozen());
  absl::StatusOr<Eigen::Isometry3d> a =
      model->PredictMotion(t.images[0], t.images[2]);
  absl::StatusOr<Eigen::Isometry3d> b =
      (*loaded)->PredictMotion(t.images[0], t.images[2]);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_LT((a->matrix() - b->matrix()).norm(), 1e-9);

  std::unique_ptr<DepthPoseModel> other = SmallModel(/*seed=*/5);
  ASSERT_TRUE(other->CopyWeightsFrom(*model).ok());
  absl::StatusOr<Eigen::Isometry3d> c =
      other->PredictMotion(t.images[0], t.images[2]);
  ASSERT_TRUE(c.ok());
  EXPECT_LT((a->matrix() - c->matrix()).norm(), 1e-9);

  EXPECT_EQ(DepthPoseModel::Load(path + ".missing").status().code(),
            absl::StatusCode::kNotFound);
  const std::string junk = testing::TempDir() + "/junk.pt";
  std::ofstream(junk) << "not a model";
  EXPECT_EQ(DepthPoseModel::Load(junk).status().code(),
            absl::StatusCode::kDataLoss);
  std::remove(path.c_str());
  std::remove(junk.c_str());
}

}  // namespace
}  // namespace fleetmem::vo
