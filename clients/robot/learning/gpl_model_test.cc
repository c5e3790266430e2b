#include "clients/robot/learning/gpl_model.h"

#include <cmath>
#include <cstdio>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot::gpl {
namespace {

std::vector<cv::Mat> RandomImages(int n, int w, int h, uint64_t seed) {
  cv::RNG rng(seed);
  std::vector<cv::Mat> images;
  for (int i = 0; i < n; ++i) {
    cv::Mat m(h, w, CV_8UC1);
    rng.fill(m, cv::RNG::UNIFORM, 0, 256);
    images.push_back(m);
  }
  return images;
}

std::unique_ptr<GplModel> NewModel(GplOptions options = {}) {
  absl::StatusOr<std::unique_ptr<GplModel>> model =
      GplModel::Create(options, "gpl-test-v1");
  EXPECT_TRUE(model.ok()) << model.status();
  return model.ok() ? *std::move(model) : nullptr;
}

TEST(GplModelTest, ShapesOfCodesDescriptorsAndDecodedImages) {
  auto model = NewModel();
  ASSERT_NE(model, nullptr);
  EXPECT_EQ(model->code_dimension(), 256);
  EXPECT_EQ(model->descriptor_dimension(), 32 * 16);
  EXPECT_GT(model->ParameterCount(), 10000);
  // Any input size and 1 or 3 channels: resized to 64 x 32.
  std::vector<cv::Mat> images = RandomImages(3, 64, 32, 1);
  cv::Mat colour(50, 90, CV_8UC3, cv::Scalar(10, 200, 30));
  images.push_back(colour);
  absl::StatusOr<std::vector<std::vector<float>>> codes = model->Encode(images);
  ASSERT_TRUE(codes.ok()) << codes.status();
  ASSERT_EQ(codes->size(), 4u);
  for (const auto& z : *codes) EXPECT_EQ(z.size(), 256u);
  absl::StatusOr<std::vector<std::vector<float>>> d = model->Describe(*codes);
  ASSERT_TRUE(d.ok()) << d.status();
  for (const auto& f : *d) {
    ASSERT_EQ(f.size(), 512u);
    double norm = 0;
    for (float v : f) norm += v * v;
    EXPECT_NEAR(norm, 1.0, 1e-4);  // unit descriptors
  }
  absl::StatusOr<std::vector<cv::Mat>> decoded = model->Decode(*codes);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ((*decoded)[0].cols, 64);
  EXPECT_EQ((*decoded)[0].rows, 32);
  EXPECT_EQ((*decoded)[0].type(), CV_8UC1);
  absl::StatusOr<std::vector<std::vector<float>>> again =
      model->Reencode(*codes);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ((*again)[0].size(), 256u);
}

TEST(GplModelTest, BadOptionsAndInputsAreRefused) {
  GplOptions odd;
  odd.image_width = 60;
  EXPECT_EQ(GplModel::Create(odd, "v").status().code(),
            absl::StatusCode::kInvalidArgument);
  GplOptions dim;
  dim.code_dimension = 100;  // not a multiple of the 32 cells
  EXPECT_EQ(GplModel::Create(dim, "v").status().code(),
            absl::StatusCode::kInvalidArgument);
  auto model = NewModel();
  std::vector<cv::Mat> empty{cv::Mat()};
  EXPECT_EQ(model->Encode(empty).status().code(),
            absl::StatusCode::kInvalidArgument);
  std::vector<std::vector<float>> wrong{std::vector<float>(10, 0.0f)};
  EXPECT_EQ(model->Describe(wrong).status().code(),
            absl::StatusCode::kInvalidArgument);
  CodeTriplets uneven;
  uneven.anchors = {std::vector<float>(256, 0.0f)};
  EXPECT_EQ(model->TrainPlaceHead(uneven).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// Eq. 7 on hand-made triplets: identical anchor, positive and negative give
// exactly the margin; anchor == positive gives max(alpha - d(a,n)^2, 0).
TEST(GplModelTest, TripletLossMatchesHandComputedValues) {
  GplOptions options;
  options.margin = 0.3f;
  auto model = NewModel(options);
  auto codes = *model->Encode(RandomImages(2, 64, 32, 7));
  ASSERT_TRUE(
      model->InitialisePlaceHead(*model->Encode(RandomImages(16, 64, 32, 8)))
          .ok());
  CodeTriplets same;
  same.anchors = {codes[0]};
  same.positives = {codes[0]};
  same.negatives = {codes[0]};
  EXPECT_NEAR((*model->TripletLosses(same))[0], 0.3f, 1e-6);

  auto d = *model->Describe(codes);
  double dan = 0;
  for (size_t i = 0; i < d[0].size(); ++i)
    dan += (d[0][i] - d[1][i]) * (d[0][i] - d[1][i]);
  CodeTriplets easy;
  easy.anchors = {codes[0]};
  easy.positives = {codes[0]};
  easy.negatives = {codes[1]};
  EXPECT_NEAR((*model->TripletLosses(easy))[0], std::max(0.0, 0.3 - dan), 1e-5);
  // Swapping positive and negative: d(a,p)^2 + alpha - 0.
  CodeTriplets hard;
  hard.anchors = {codes[0]};
  hard.positives = {codes[1]};
  hard.negatives = {codes[0]};
  EXPECT_NEAR((*model->TripletLosses(hard))[0], dan + 0.3, 1e-5);
}

TEST(GplModelTest, TrainingTheHeadLowersTheTripletLoss) {
  auto model = NewModel();
  auto codes = *model->Encode(RandomImages(24, 64, 32, 3));
  CodeTriplets batch;
  for (int i = 0; i < 8; ++i) {
    batch.anchors.push_back(codes[i]);
    batch.positives.push_back(codes[i + 8]);
    batch.negatives.push_back(codes[i + 16]);
  }
  const float before = (*model->TrainPlaceHead(batch)).loc;
  float after = before;
  for (int step = 0; step < 60; ++step)
    after = (*model->TrainPlaceHead(batch)).loc;
  EXPECT_LT(after, before * 0.5f) << before << " -> " << after;
}

TEST(GplModelTest, FrozenEncoderKeepsItsCodesWhileHeadAndDecoderLearn) {
  auto model = NewModel();
  auto images = RandomImages(8, 64, 32, 5);
  ImageTriplets joint;
  joint.anchors = {images[0], images[1]};
  joint.positives = {images[2], images[3]};
  joint.negatives = {images[4], images[5]};
  ASSERT_TRUE(model->TrainJoint(joint).ok());
  model->FreezeEncoder();
  auto before = *model->Encode(images);
  EXPECT_EQ(model->TrainJoint(joint).status().code(),
            absl::StatusCode::kFailedPrecondition);
  absl::StatusOr<StepLosses> g = model->TrainGenerative(images);
  ASSERT_TRUE(g.ok()) << g.status();
  EXPECT_TRUE(std::isfinite(g->rec) && std::isfinite(g->gan_g) &&
              std::isfinite(g->gan_d));
  CodeTriplets batch{{before[0]}, {before[1]}, {before[2]}};
  ASSERT_TRUE(model->TrainPlaceHead(batch).ok());
  EXPECT_EQ(*model->Encode(images), before);
}

TEST(GplModelTest, SaveAndLoadRoundTripKeepsVersionOptionsAndOutputs) {
  GplOptions options;
  options.code_dimension = 512;
  options.wrap_horizontal = true;
  options.seed = 9;
  auto model = NewModel(options);
  model->set_version("gpl-roundtrip-v3");
  model->FreezeEncoder();
  auto images = RandomImages(4, 64, 32, 11);
  auto codes = *model->Encode(images);
  auto descriptors = *model->Describe(codes);
  const std::string path = ::testing::TempDir() + "/gpl-roundtrip-" +
                           std::to_string(::getpid()) + ".pt";
  ASSERT_TRUE(model->Save(path).ok());
  absl::StatusOr<std::unique_ptr<GplModel>> loaded = GplModel::Load(path);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ((*loaded)->version(), "gpl-roundtrip-v3");
  EXPECT_EQ((*loaded)->code_dimension(), 512);
  EXPECT_TRUE((*loaded)->options().wrap_horizontal);
  EXPECT_TRUE((*loaded)->encoder_frozen());
  EXPECT_EQ(*(*loaded)->Encode(images), codes);
  EXPECT_EQ(*(*loaded)->Describe(codes), descriptors);
  auto clone = model->Clone();
  ASSERT_TRUE(clone.ok());
  EXPECT_EQ(*(*clone)->Describe(codes), descriptors);
  std::remove(path.c_str());

  EXPECT_EQ(GplModel::Load(path).status().code(), absl::StatusCode::kNotFound);
  const std::string junk = path + ".junk";
  FILE* f = std::fopen(junk.c_str(), "w");
  std::fputs("not a model", f);
  std::fclose(f);
  EXPECT_EQ(GplModel::Load(junk).status().code(), absl::StatusCode::kDataLoss);
  std::remove(junk.c_str());
}

TEST(GplModelTest, WrapAroundMakesTheDescriptorNearlyRotationInvariant) {
  GplOptions options;
  options.wrap_horizontal = true;
  auto model = NewModel(options);
  cv::Mat image = RandomImages(1, 64, 32, 13)[0];
  // A rotation by a multiple of the code's cell (8 px) only permutes the
  // cells: NetVLAD sums over cells, so the descriptor is unchanged.
  cv::Mat rolled(image.size(), image.type());
  image.colRange(0, 48).copyTo(rolled.colRange(16, 64));
  image.colRange(48, 64).copyTo(rolled.colRange(0, 16));
  std::vector<cv::Mat> both{image, rolled};
  auto d = *model->Describe(*model->Encode(both));
  for (size_t i = 0; i < d[0].size(); ++i) EXPECT_NEAR(d[0][i], d[1][i], 1e-4);
}

}  // namespace
}  // namespace fleetmem::robot::gpl
