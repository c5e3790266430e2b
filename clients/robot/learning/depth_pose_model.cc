// libtorch implementation of the depth and pose networks
// (depth_pose_model.h). Every libtorch exception stops here and becomes a
// status.
#include "clients/robot/learning/depth_pose_model.h"

#include <ATen/CPUGeneratorImpl.h>
#include <torch/torch.h>

#include <cmath>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/learning/torch_archive.h"
#include "opencv2/imgproc.hpp"

namespace fleetmem::vo {
namespace {

namespace F = torch::nn::functional;

constexpr int64_t kFormat = 1;
constexpr char kMagic[] = "fleetmem-depth-pose";
constexpr int kScales = 4;
constexpr std::array<int, 5> kEncoderChannels = {16, 32, 64, 96, 128};
constexpr std::array<int, 5> kDecoderChannels = {16, 16, 32, 64, 96};
constexpr int kPoseChannels = 128;

torch::nn::Conv2d Conv(int in, int out, int kernel, int stride = 1) {
  return torch::nn::Conv2d(torch::nn::Conv2dOptions(in, out, kernel)
                               .stride(stride)
                               .padding(kernel / 2));
}

// Five stride-2 stages of two 3x3 convolutions with ELU; returns the output
// of every stage (H/2 ... H/32).
struct EncoderImpl : torch::nn::Module {
  explicit EncoderImpl(int in_channels) {
    int in = in_channels;
    for (size_t i = 0; i < kEncoderChannels.size(); ++i) {
      const int out = kEncoderChannels[i];
      down.push_back(
          register_module(absl::StrCat("down", i), Conv(in, out, 3, 2)));
      same.push_back(
          register_module(absl::StrCat("same", i), Conv(out, out, 3)));
      in = out;
    }
  }
  std::vector<torch::Tensor> forward(torch::Tensor x) {
    std::vector<torch::Tensor> features;
    x = (x - 0.45) / 0.225;
    for (size_t i = 0; i < down.size(); ++i) {
      x = torch::elu(same[i]->forward(torch::elu(down[i]->forward(x))));
      features.push_back(x);
    }
    return features;
  }
  std::vector<torch::nn::Conv2d> down;
  std::vector<torch::nn::Conv2d> same;
};
TORCH_MODULE(Encoder);

// Monodepth2's decoder: upsample, concatenate the encoder's skip, and a
// sigmoid disparity at scales 0..3 (full size ... 1/8).
struct DepthDecoderImpl : torch::nn::Module {
  DepthDecoderImpl() {
    for (int i = 4; i >= 0; --i) {
      const int in0 = i == 4 ? kEncoderChannels[4] : kDecoderChannels[i + 1];
      up0[i] = register_module(absl::StrCat("up0_", i),
                               Conv(in0, kDecoderChannels[i], 3));
      const int in1 =
          kDecoderChannels[i] + (i > 0 ? kEncoderChannels[i - 1] : 0);
      up1[i] = register_module(absl::StrCat("up1_", i),
                               Conv(in1, kDecoderChannels[i], 3));
      if (i < kScales) {
        disp[i] = register_module(absl::StrCat("disp", i),
                                  Conv(kDecoderChannels[i], 1, 3));
        // sigmoid(-4.6) = 0.01: the untrained network sees everything about
        // 9 m away. At sigmoid(0) = 0.5 it would see 0.2 m, where every
        // warp leaves the image (border samples carry no gradient) and
        // training from scratch never starts.
        torch::NoGradGuard no_grad;
        disp[i]->bias.fill_(-4.6);
      }
    }
  }
  std::vector<torch::Tensor> forward(const std::vector<torch::Tensor>& feats) {
    std::vector<torch::Tensor> out(kScales);
    torch::Tensor x = feats[4];
    for (int i = 4; i >= 0; --i) {
      x = torch::elu(up0[i]->forward(x));
      x = F::interpolate(x, F::InterpolateFuncOptions()
                                .scale_factor(std::vector<double>{2.0, 2.0})
                                .mode(torch::kNearest));
      if (i > 0) x = torch::cat({x, feats[i - 1]}, 1);
      x = torch::elu(up1[i]->forward(x));
      if (i < kScales) out[i] = torch::sigmoid(disp[i]->forward(x));
    }
    return out;
  }
  std::array<torch::nn::Conv2d, 5> up0{nullptr, nullptr, nullptr, nullptr,
                                       nullptr};
  std::array<torch::nn::Conv2d, 5> up1{nullptr, nullptr, nullptr, nullptr,
                                       nullptr};
  std::array<torch::nn::Conv2d, kScales> disp{nullptr, nullptr, nullptr,
                                              nullptr};
};
TORCH_MODULE(DepthDecoder);

// Monodepth2's pose decoder: squeeze, two 3x3 convolutions, 6 outputs
// averaged over the image. Monodepth2 scales all six by 0.01; here only the
// rotation is, so that metre-sized translations (KITTI: ~1 m per frame) are
// O(1) outputs that a few hundred CPU steps can reach.
struct PoseDecoderImpl : torch::nn::Module {
  PoseDecoderImpl() {
    squeeze =
        register_module("squeeze", Conv(kEncoderChannels[4], kPoseChannels, 1));
    c1 = register_module("c1", Conv(kPoseChannels, kPoseChannels, 3));
    c2 = register_module("c2", Conv(kPoseChannels, kPoseChannels, 3));
    out = register_module("out", Conv(kPoseChannels, 6, 1));
    // A forward-looking camera moves along its optical axis: the untrained
    // network starts at 1 m forward per frame instead of a random
    // direction. Without this prior, pre-training from scratch lands in a
    // basin with the wrong direction of travel for some seeds (the
    // velocity term fixes only the length).
    torch::NoGradGuard no_grad;
    out->bias.zero_();
    out->bias[5].fill_(1.0);
  }
  torch::Tensor forward(const torch::Tensor& bottleneck) {
    torch::Tensor x = torch::relu(squeeze->forward(bottleneck));
    x = torch::relu(c1->forward(x));
    x = torch::relu(c2->forward(x));
    const torch::Tensor p = out->forward(x).mean({2, 3});
    return torch::cat({0.01 * p.slice(1, 0, 3), p.slice(1, 3, 6)}, 1);
  }
  torch::nn::Conv2d squeeze{nullptr}, c1{nullptr}, c2{nullptr}, out{nullptr};
};
TORCH_MODULE(PoseDecoder);

absl::Status ValidateOptions(const DepthPoseOptions& o) {
  if (o.image_width <= 0 || o.image_height <= 0 || o.image_width % 32 != 0 ||
      o.image_height % 32 != 0) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "image size %dx%d: width and height must be positive multiples of 32",
        o.image_width, o.image_height));
  }
  if (!(o.min_depth_m > 0.0) || !(o.max_depth_m > o.min_depth_m)) {
    return absl::InvalidArgumentError(
        "depth range: need 0 < min_depth_m < max_depth_m");
  }
  if (!(o.smoothness_weight >= 0.0f) || !(o.velocity_weight >= 0.0f) ||
      !(o.ssim_weight >= 0.0f && o.ssim_weight <= 1.0f) ||
      !(o.learning_rate > 0.0)) {
    return absl::InvalidArgumentError(
        "weights must be >= 0, ssim_weight <= 1, learning_rate > 0");
  }
  return absl::OkStatus();
}

torch::Tensor OptionsToTensor(const DepthPoseOptions& o) {
  return torch::tensor(
      std::vector<double>{
          double(o.image_width), double(o.image_height), o.min_depth_m,
          o.max_depth_m, double(o.smoothness_weight), double(o.velocity_weight),
          double(o.ssim_weight), o.learning_rate, double(o.seed)},
      torch::kFloat64);
}

absl::StatusOr<DepthPoseOptions> OptionsFromTensor(const torch::Tensor& t) {
  if (t.dim() != 1 || t.size(0) != 9 || t.scalar_type() != torch::kFloat64) {
    return absl::DataLossError("the options record has the wrong shape");
  }
  auto v = t.accessor<double, 1>();
  DepthPoseOptions o;
  o.image_width = int(v[0]);
  o.image_height = int(v[1]);
  o.min_depth_m = v[2];
  o.max_depth_m = v[3];
  o.smoothness_weight = float(v[4]);
  o.velocity_weight = float(v[5]);
  o.ssim_weight = float(v[6]);
  o.learning_rate = v[7];
  o.seed = uint64_t(v[8]);
  return o;
}

template <typename T, typename Body>
absl::StatusOr<T> Guarded(const char* what, Body&& body) {
  return robot::learning::Guarded<T>("vo", what, std::forward<Body>(body));
}

// An 8-bit or float grey (or BGR) image as a 1 x 1 x H x W tensor in [0, 1]
// at width x height (INTER_AREA when shrinking).
absl::StatusOr<torch::Tensor> ImageTensor(const cv::Mat& image, int width,
                                          int height) {
  if (image.empty()) return absl::InvalidArgumentError("empty image");
  cv::Mat grey = image;
  if (image.channels() == 3) cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
  if (grey.channels() != 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("images need 1 or 3 channels, not ", grey.channels()));
  }
  cv::Mat sized;
  if (grey.cols != width || grey.rows != height) {
    cv::resize(grey, sized, cv::Size(width, height), 0, 0, cv::INTER_AREA);
  } else {
    sized = grey;
  }
  cv::Mat f;
  sized.convertTo(f, CV_32F, 1.0 / 255.0);
  return torch::from_blob(f.data, {1, 1, height, width}, torch::kFloat32)
      .clone();
}

// K (3 x 3) of a camera.
torch::Tensor Intrinsics(const Camera& c) {
  return torch::tensor({float(c.fx), 0.0f, float(c.cx), 0.0f, float(c.fy),
                        float(c.cy), 0.0f, 0.0f, 1.0f})
      .view({3, 3});
}

// B x 4 x 4 isometries from B x 6 parameters (axis-angle, translation) by
// Rodrigues' formula.
torch::Tensor TransformFromParameters(const torch::Tensor& p) {
  const torch::Tensor aa = p.slice(1, 0, 3);
  const torch::Tensor t = p.slice(1, 3, 6);
  const torch::Tensor angle = aa.norm(2, 1, true);
  const torch::Tensor axis = aa / (angle + 1e-7);
  const torch::Tensor ca = torch::cos(angle), sa = torch::sin(angle);
  const torch::Tensor c = 1 - ca;
  const torch::Tensor x = axis.slice(1, 0, 1), y = axis.slice(1, 1, 2),
                      z = axis.slice(1, 2, 3);
  const torch::Tensor r =
      torch::cat({x * x * c + ca, x * y * c - z * sa, x * z * c + y * sa,  //
                  y * x * c + z * sa, y * y * c + ca, y * z * c - x * sa,  //
                  z * x * c - y * sa, z * y * c + x * sa, z * z * c + ca},
                 1);
  const int64_t b = p.size(0);
  torch::Tensor top = torch::cat({r.view({b, 3, 3}), t.view({b, 3, 1})}, 2);
  torch::Tensor bottom =
      torch::tensor({0.0f, 0.0f, 0.0f, 1.0f}).view({1, 1, 4}).expand({b, 1, 4});
  return torch::cat({top, bottom}, 1);
}

torch::Tensor InvertTransform(const torch::Tensor& t) {
  const torch::Tensor rt = t.slice(1, 0, 3).slice(2, 0, 3).transpose(1, 2);
  const torch::Tensor tr = t.slice(1, 0, 3).slice(2, 3, 4);
  const int64_t b = t.size(0);
  torch::Tensor bottom =
      torch::tensor({0.0f, 0.0f, 0.0f, 1.0f}).view({1, 1, 4}).expand({b, 1, 4});
  return torch::cat({torch::cat({rt, -torch::bmm(rt, tr)}, 2), bottom}, 1);
}

// The sampling grid (B x H x W x 2, grid_sample's [-1, 1] coordinates with
// align_corners = false) of the target pixels' projections into a source
// camera: X_source = target_to_source * depth * K^-1 [u v 1]^T.
torch::Tensor ProjectionGrid(const torch::Tensor& depth, const torch::Tensor& k,
                             const torch::Tensor& target_to_source) {
  const int64_t b = depth.size(0), h = depth.size(2), w = depth.size(3);
  const torch::Tensor ys = torch::arange(h, torch::kFloat32);
  const torch::Tensor xs = torch::arange(w, torch::kFloat32);
  std::vector<torch::Tensor> mesh = torch::meshgrid({ys, xs}, "ij");
  const torch::Tensor pixels =
      torch::stack({mesh[1].reshape(-1), mesh[0].reshape(-1),
                    torch::ones({h * w}, torch::kFloat32)})
          .unsqueeze(0)
          .expand({b, 3, h * w});
  const torch::Tensor rays = torch::bmm(torch::inverse(k), pixels);
  const torch::Tensor points = rays * depth.view({b, 1, h * w});
  const torch::Tensor moved =
      torch::bmm(target_to_source.slice(1, 0, 3).slice(2, 0, 3), points) +
      target_to_source.slice(1, 0, 3).slice(2, 3, 4);
  const torch::Tensor projected = torch::bmm(k, moved);
  const torch::Tensor z = projected.slice(1, 2, 3).clamp_min(1e-3);
  const torch::Tensor u = projected.slice(1, 0, 1) / z;
  const torch::Tensor v = projected.slice(1, 1, 2) / z;
  const torch::Tensor gx = (2 * u + 1) / double(w) - 1;
  const torch::Tensor gy = (2 * v + 1) / double(h) - 1;
  return torch::cat({gx, gy}, 1).permute({0, 2, 1}).reshape({b, h, w, 2});
}

torch::Tensor Warp(const torch::Tensor& source, const torch::Tensor& grid) {
  return F::grid_sample(source, grid,
                        F::GridSampleFuncOptions()
                            .mode(torch::kBilinear)
                            .padding_mode(torch::kBorder)
                            .align_corners(false));
}

// Monodepth2's SSIM dissimilarity (1 - SSIM) / 2 on 3x3 windows with
// reflection padding, clamped to [0, 1].
torch::Tensor Dssim(const torch::Tensor& a, const torch::Tensor& b) {
  const auto pad = F::PadFuncOptions({1, 1, 1, 1}).mode(torch::kReflect);
  const torch::Tensor x = F::pad(a, pad), y = F::pad(b, pad);
  const auto pool = [](const torch::Tensor& t) {
    return F::avg_pool2d(t, F::AvgPool2dFuncOptions(3).stride(1));
  };
  const torch::Tensor mx = pool(x), my = pool(y);
  const torch::Tensor sx = pool(x * x) - mx * mx;
  const torch::Tensor sy = pool(y * y) - my * my;
  const torch::Tensor sxy = pool(x * y) - mx * my;
  constexpr double c1 = 0.01 * 0.01, c2 = 0.03 * 0.03;
  const torch::Tensor n = (2 * mx * my + c1) * (2 * sxy + c2);
  const torch::Tensor d = (mx * mx + my * my + c1) * (sx + sy + c2);
  return torch::clamp((1 - n / d) / 2, 0, 1);
}

// Per-pixel photometric error B x 1 x H x W.
torch::Tensor PhotometricError(const torch::Tensor& predicted,
                               const torch::Tensor& target, float ssim_weight) {
  const torch::Tensor l1 = (predicted - target).abs().mean(1, true);
  return ssim_weight * Dssim(predicted, target).mean(1, true) +
         (1 - ssim_weight) * l1;
}

// The per-pixel minimum of the warped sources' errors and, with automask,
// of the unwarped sources' (plus a 1e-5 tie-breaking noise, Monodepth2,
// drawn from the model's own generator: two models trained side by side do
// not disturb each other's draws).
torch::Tensor MinimumReprojection(const torch::Tensor& target,
                                  const std::vector<torch::Tensor>& warped,
                                  const std::vector<torch::Tensor>& sources,
                                  bool automask, float ssim_weight,
                                  at::Generator& generator) {
  std::vector<torch::Tensor> errors;
  for (const torch::Tensor& w : warped) {
    errors.push_back(PhotometricError(w, target, ssim_weight));
  }
  if (automask) {
    for (const torch::Tensor& s : sources) {
      torch::Tensor identity = PhotometricError(s, target, ssim_weight);
      errors.push_back(
          identity +
          at::randn(identity.sizes(), generator, identity.options()) * 1e-5);
    }
  }
  return std::get<0>(torch::cat(errors, 1).min(1));
}

// Edge-aware smoothness of the mean-normalised disparity.
torch::Tensor Smoothness(const torch::Tensor& disp,
                         const torch::Tensor& image) {
  const torch::Tensor d = disp / (disp.mean({2, 3}, true) + 1e-7);
  const auto dx = [](const torch::Tensor& t) {
    return (t.slice(3, 0, -1) - t.slice(3, 1)).abs();
  };
  const auto dy = [](const torch::Tensor& t) {
    return (t.slice(2, 0, -1) - t.slice(2, 1)).abs();
  };
  const torch::Tensor gx = dx(d) * torch::exp(-dx(image).mean(1, true));
  const torch::Tensor gy = dy(d) * torch::exp(-dy(image).mean(1, true));
  return gx.mean() + gy.mean();
}

cv::Mat ToFloatImage(const cv::Mat& image) {
  cv::Mat f;
  image.convertTo(f, CV_32F, 1.0 / 255.0);
  return f;
}

torch::Tensor MatTensor(const cv::Mat& m) {
  cv::Mat c = m.isContinuous() ? m : m.clone();
  return torch::from_blob(c.data, {1, 1, c.rows, c.cols}, torch::kFloat32)
      .clone();
}

torch::Tensor IsometryTensor(const Eigen::Isometry3d& t) {
  std::vector<float> v(16);
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) v[r * 4 + c] = float(t.matrix()(r, c));
  }
  return torch::tensor(v).view({1, 4, 4});
}

}  // namespace

Camera ResizedCamera(const Camera& camera, int width, int height) {
  const double sx = double(width) / camera.width;
  const double sy = double(height) / camera.height;
  Camera c = camera;
  c.fx = camera.fx * sx;
  c.fy = camera.fy * sy;
  c.cx = (camera.cx + 0.5) * sx - 0.5;
  c.cy = (camera.cy + 0.5) * sy - 0.5;
  c.width = width;
  c.height = height;
  return c;
}

struct DepthPoseModel::Impl {
  explicit Impl(const DepthPoseOptions& o) : options(o) {
    generator = at::make_generator<at::CPUGeneratorImpl>(o.seed);
    depth_encoder = Encoder(1);
    depth_decoder = DepthDecoder();
    pose_encoder = Encoder(2);
    pose_decoder = PoseDecoder();
    ResetOptimizer();
  }

  std::vector<std::pair<std::string, torch::nn::Module*>> Modules() {
    return {{"depth_encoder", depth_encoder.get()},
            {"depth_decoder", depth_decoder.get()},
            {"pose_encoder", pose_encoder.get()},
            {"pose_decoder", pose_decoder.get()}};
  }

  void ResetOptimizer() {
    std::vector<torch::Tensor> trainable;
    for (auto& [name, module] : Modules()) {
      for (torch::Tensor& p : module->parameters()) {
        if (p.requires_grad()) trainable.push_back(p);
      }
    }
    optimizer = std::make_unique<torch::optim::Adam>(
        trainable, torch::optim::AdamOptions(options.learning_rate));
  }

  void Freeze() {
    for (torch::nn::Module* m :
         {static_cast<torch::nn::Module*>(depth_encoder.get()),
          static_cast<torch::nn::Module*>(pose_encoder.get())}) {
      for (torch::Tensor& p : m->parameters()) p.set_requires_grad(false);
    }
    frozen = true;
    ResetOptimizer();
  }

  absl::StatusOr<torch::Tensor> Input(const cv::Mat& image) const {
    return ImageTensor(image, options.image_width, options.image_height);
  }

  torch::Tensor DispToDepth(const torch::Tensor& disp) const {
    const double min_disp = 1.0 / options.max_depth_m;
    const double max_disp = 1.0 / options.min_depth_m;
    return 1.0 / (min_disp + (max_disp - min_disp) * disp);
  }

  // Pose parameters of each pair (first, second).
  torch::Tensor PoseParameters(const torch::Tensor& first,
                               const torch::Tensor& second) {
    return pose_decoder->forward(
        pose_encoder->forward(torch::cat({first, second}, 1)).back());
  }

  // Eq. 7 over a batch; the caller steps or not.
  absl::StatusOr<std::pair<torch::Tensor, VoLosses>> Loss(
      std::span<const Triplet> batch) {
    if (batch.empty()) return absl::InvalidArgumentError("empty batch");
    const int w = options.image_width, h = options.image_height;
    std::vector<torch::Tensor> prev, mid, next, right, ks, dist;
    bool stereo = true;
    for (const Triplet& t : batch) {
      if (!(t.camera.fx > 0.0) || !(t.camera.fy > 0.0) || t.camera.width <= 0 ||
          t.camera.height <= 0) {
        return absl::InvalidArgumentError(
            "a triplet's camera lacks its focal length or image size");
      }
      for (const cv::Mat& image : t.images) {
        if (image.empty()) return absl::InvalidArgumentError("empty image");
      }
      absl::StatusOr<torch::Tensor> a = Input(t.images[0]);
      absl::StatusOr<torch::Tensor> b = Input(t.images[1]);
      absl::StatusOr<torch::Tensor> c = Input(t.images[2]);
      if (!a.ok()) return a.status();
      if (!b.ok()) return b.status();
      if (!c.ok()) return c.status();
      prev.push_back(*a);
      mid.push_back(*b);
      next.push_back(*c);
      ks.push_back(Intrinsics(ResizedCamera(t.camera, w, h)));
      dist.push_back(
          torch::tensor({float(t.distances_m[0]), float(t.distances_m[1])}));
      if (t.right_of_middle.empty() || !(t.camera.baseline_m > 0.0)) {
        stereo = false;
      } else {
        absl::StatusOr<torch::Tensor> r = Input(t.right_of_middle);
        if (!r.ok()) return r.status();
        right.push_back(*r);
      }
    }
    const torch::Tensor i0 = torch::cat(prev), i1 = torch::cat(mid),
                        i2 = torch::cat(next);
    const torch::Tensor k = torch::stack(ks);

    const std::vector<torch::Tensor> disps =
        depth_decoder->forward(depth_encoder->forward(i1));
    const torch::Tensor p01 = PoseParameters(i0, i1);
    const torch::Tensor p12 = PoseParameters(i1, i2);
    // Target (middle) to source: X_0 = T_01 X_1; X_2 = T_12^-1 X_1.
    std::vector<torch::Tensor> to_source = {
        TransformFromParameters(p01),
        InvertTransform(TransformFromParameters(p12))};
    std::vector<torch::Tensor> sources = {i0, i2};
    if (stereo) {
      std::vector<torch::Tensor> offsets;
      for (const Triplet& t : batch) {
        Eigen::Isometry3d right_in_left = Eigen::Isometry3d::Identity();
        right_in_left.translation().x() = t.camera.baseline_m;
        offsets.push_back(IsometryTensor(right_in_left.inverse()));
      }
      to_source.push_back(torch::cat(offsets));
      sources.push_back(torch::cat(right));
    }

    torch::Tensor photometric = torch::zeros({});
    torch::Tensor smoothness = torch::zeros({});
    for (int s = 0; s < kScales; ++s) {
      const torch::Tensor disp =
          F::interpolate(disps[s], F::InterpolateFuncOptions()
                                       .size(std::vector<int64_t>{h, w})
                                       .mode(torch::kBilinear)
                                       .align_corners(false));
      const torch::Tensor depth = DispToDepth(disp);
      std::vector<torch::Tensor> warped;
      for (size_t j = 0; j < sources.size(); ++j) {
        warped.push_back(
            Warp(sources[j], ProjectionGrid(depth, k, to_source[j])));
      }
      photometric =
          photometric + MinimumReprojection(i1, warped, sources,
                                            /*automask=*/true,
                                            options.ssim_weight, generator)
                            .mean();
      const torch::Tensor target_s =
          s == 0
              ? i1
              : F::interpolate(i1, F::InterpolateFuncOptions()
                                       .size(std::vector<int64_t>{
                                           disps[s].size(2), disps[s].size(3)})
                                       .mode(torch::kArea));
      smoothness = smoothness + Smoothness(disps[s], target_s) / double(1 << s);
    }
    photometric = photometric / double(kScales);
    smoothness = smoothness / double(kScales);
    const torch::Tensor travelled = torch::stack(dist);  // B x 2
    const torch::Tensor norms = torch::stack(
        {p01.slice(1, 3, 6).norm(2, 1), p12.slice(1, 3, 6).norm(2, 1)}, 1);
    const torch::Tensor velocity = (norms - travelled).abs().mean();
    const torch::Tensor total = photometric +
                                options.smoothness_weight * smoothness +
                                options.velocity_weight * velocity;
    VoLosses losses{total.item<float>(), photometric.item<float>(),
                    smoothness.item<float>(), velocity.item<float>()};
    return std::make_pair(total, losses);
  }

  DepthPoseOptions options;
  Encoder depth_encoder{nullptr};
  DepthDecoder depth_decoder{nullptr};
  Encoder pose_encoder{nullptr};
  PoseDecoder pose_decoder{nullptr};
  std::unique_ptr<torch::optim::Adam> optimizer;
  // The auto-mask's noise; seeded with options.seed (a clone starts afresh).
  at::Generator generator = at::make_generator<at::CPUGeneratorImpl>(0);
  bool frozen = false;
};

DepthPoseModel::DepthPoseModel(std::unique_ptr<Impl> impl)
    : impl_(std::move(impl)) {}
DepthPoseModel::~DepthPoseModel() = default;

absl::StatusOr<std::unique_ptr<DepthPoseModel>> DepthPoseModel::Create(
    const DepthPoseOptions& options) {
  if (absl::Status valid = ValidateOptions(options); !valid.ok()) return valid;
  return Guarded<std::unique_ptr<DepthPoseModel>>("create", [&] {
    torch::manual_seed(options.seed);
    return std::unique_ptr<DepthPoseModel>(
        new DepthPoseModel(std::make_unique<Impl>(options)));
  });
}

absl::Status DepthPoseModel::Save(const std::string& path) const {
  return robot::learning::SaveModelArchive(
      path, kMagic, kFormat,
      [&](torch::serialize::OutputArchive& archive) {
        archive.write("encoders_frozen", c10::IValue(impl_->frozen));
        archive.write("options", OptionsToTensor(impl_->options));
      },
      impl_->Modules());
}

absl::StatusOr<std::unique_ptr<DepthPoseModel>> DepthPoseModel::Load(
    const std::string& path) {
  torch::serialize::InputArchive archive;
  if (absl::Status s = robot::learning::OpenModelArchive(
          path, kMagic, kFormat, "depth and pose model", archive);
      !s.ok()) {
    return s;
  }
  c10::IValue frozen;
  torch::Tensor options_tensor;
  if (!archive.try_read("encoders_frozen", frozen) || !frozen.isBool() ||
      !archive.try_read("options", options_tensor)) {
    return absl::DataLossError(absl::StrCat(path, " lacks its options"));
  }
  absl::StatusOr<DepthPoseOptions> options = OptionsFromTensor(options_tensor);
  if (!options.ok()) return options.status();
  if (absl::Status valid = ValidateOptions(*options); !valid.ok()) {
    return absl::DataLossError(absl::StrCat(path, ": ", valid.message()));
  }
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> model = Create(*options);
  if (!model.ok()) return model.status();
  try {
    robot::learning::ReadModules(archive, (*model)->impl_->Modules());
  } catch (const std::exception& e) {
    return absl::DataLossError(
        absl::StrCat(path, ": the weights do not match the options: ",
                     robot::learning::TorchMessage(e)));
  }
  if (frozen.toBool()) (*model)->FreezeEncoders();
  return model;
}

absl::StatusOr<std::unique_ptr<DepthPoseModel>> DepthPoseModel::Clone() const {
  absl::StatusOr<std::unique_ptr<DepthPoseModel>> copy = Create(impl_->options);
  if (!copy.ok()) return copy.status();
  if (impl_->frozen) (*copy)->FreezeEncoders();
  if (absl::Status s = (*copy)->CopyWeightsFrom(*this); !s.ok()) return s;
  return copy;
}

absl::Status DepthPoseModel::CopyWeightsFrom(const DepthPoseModel& other) {
  const DepthPoseOptions& a = impl_->options;
  const DepthPoseOptions& b = other.impl_->options;
  if (a.image_width != b.image_width || a.image_height != b.image_height) {
    return absl::InvalidArgumentError(
        "cannot copy weights between models of different input sizes");
  }
  absl::StatusOr<bool> copied = Guarded<bool>("copy", [&] {
    torch::NoGradGuard no_grad;
    auto mine = impl_->Modules();
    auto theirs = other.impl_->Modules();
    for (size_t m = 0; m < mine.size(); ++m) {
      std::vector<torch::Tensor> to = mine[m].second->parameters();
      std::vector<torch::Tensor> from = theirs[m].second->parameters();
      for (size_t i = 0; i < to.size(); ++i) to[i].copy_(from[i]);
    }
    impl_->ResetOptimizer();
    return true;
  });
  return copied.status();
}

const DepthPoseOptions& DepthPoseModel::options() const {
  return impl_->options;
}

int64_t DepthPoseModel::ParameterCount() const {
  int64_t n = 0;
  for (auto& [name, module] : impl_->Modules()) {
    for (const torch::Tensor& p : module->parameters()) n += p.numel();
  }
  return n;
}

void DepthPoseModel::FreezeEncoders() { impl_->Freeze(); }
bool DepthPoseModel::encoders_frozen() const { return impl_->frozen; }

absl::StatusOr<VoLosses> DepthPoseModel::TrainStep(
    std::span<const Triplet> batch) {
  absl::StatusOr<absl::StatusOr<VoLosses>> result =
      Guarded<absl::StatusOr<VoLosses>>(
          "train", [&]() -> absl::StatusOr<VoLosses> {
            absl::StatusOr<std::pair<torch::Tensor, VoLosses>> loss =
                impl_->Loss(batch);
            if (!loss.ok()) return loss.status();
            impl_->optimizer->zero_grad();
            loss->first.backward();
            impl_->optimizer->step();
            return loss->second;
          });
  if (!result.ok()) return result.status();
  return *result;
}

absl::StatusOr<VoLosses> DepthPoseModel::Evaluate(
    std::span<const Triplet> batch) {
  absl::StatusOr<absl::StatusOr<VoLosses>> result =
      Guarded<absl::StatusOr<VoLosses>>(
          "evaluate", [&]() -> absl::StatusOr<VoLosses> {
            torch::NoGradGuard no_grad;
            absl::StatusOr<std::pair<torch::Tensor, VoLosses>> loss =
                impl_->Loss(batch);
            if (!loss.ok()) return loss.status();
            return loss->second;
          });
  if (!result.ok()) return result.status();
  return *result;
}

absl::StatusOr<Eigen::Isometry3d> DepthPoseModel::PredictMotion(
    const cv::Mat& first, const cv::Mat& second) {
  absl::StatusOr<torch::Tensor> a = impl_->Input(first);
  if (!a.ok()) return a.status();
  absl::StatusOr<torch::Tensor> b = impl_->Input(second);
  if (!b.ok()) return b.status();
  return Guarded<Eigen::Isometry3d>("pose", [&] {
    torch::NoGradGuard no_grad;
    const torch::Tensor p = impl_->PoseParameters(*a, *b).contiguous();
    std::array<float, 6> v;
    for (int i = 0; i < 6; ++i) v[i] = p[0][i].item<float>();
    return PoseFromParameters(v);
  });
}

absl::StatusOr<cv::Mat> DepthPoseModel::PredictDepth(const cv::Mat& image) {
  absl::StatusOr<torch::Tensor> x = impl_->Input(image);
  if (!x.ok()) return x.status();
  return Guarded<cv::Mat>("depth", [&] {
    torch::NoGradGuard no_grad;
    const torch::Tensor depth = impl_
                                    ->DispToDepth(impl_->depth_decoder->forward(
                                        impl_->depth_encoder->forward(*x))[0])
                                    .contiguous();
    cv::Mat out(impl_->options.image_height, impl_->options.image_width,
                CV_32F);
    std::memcpy(out.data, depth.data_ptr<float>(), sizeof(float) * out.total());
    return out;
  });
}

absl::StatusOr<std::vector<float>> DepthPoseModel::Feature(
    const cv::Mat& image) {
  absl::StatusOr<torch::Tensor> x = impl_->Input(image);
  if (!x.ok()) return x.status();
  return Guarded<std::vector<float>>("feature", [&] {
    torch::NoGradGuard no_grad;
    const torch::Tensor f =
        impl_->depth_encoder->forward(*x).back().reshape(-1).contiguous();
    return std::vector<float>(f.data_ptr<float>(),
                              f.data_ptr<float>() + f.numel());
  });
}

Eigen::Isometry3d PoseFromParameters(const std::array<float, 6>& parameters) {
  const torch::Tensor t =
      TransformFromParameters(
          torch::tensor(
              std::vector<float>(parameters.begin(), parameters.end()))
              .view({1, 6}))
          .to(torch::kFloat64)
          .contiguous();
  Eigen::Matrix4d m;
  auto a = t.accessor<double, 3>();
  for (int r = 0; r < 4; ++r) {
    for (int c = 0; c < 4; ++c) m(r, c) = a[0][r][c];
  }
  Eigen::Isometry3d pose = Eigen::Isometry3d::Identity();
  // Re-orthonormalise the float rotation.
  pose.linear() = Eigen::Quaterniond(m.topLeftCorner<3, 3>())
                      .normalized()
                      .toRotationMatrix();
  pose.translation() = m.topRightCorner<3, 1>();
  return pose;
}

absl::StatusOr<cv::Mat> WarpToTarget(const cv::Mat& source,
                                     const cv::Mat& target_depth,
                                     const Eigen::Isometry3d& source_in_target,
                                     const Camera& camera) {
  if (source.empty() || source.channels() != 1 ||
      target_depth.type() != CV_32F || source.size() != target_depth.size() ||
      source.cols != camera.width || source.rows != camera.height) {
    return absl::InvalidArgumentError(
        "WarpToTarget: a one-channel source and a CV_32F depth of the "
        "camera's size");
  }
  return Guarded<cv::Mat>("warp", [&] {
    const torch::Tensor src = MatTensor(ToFloatImage(source));
    const torch::Tensor depth = MatTensor(target_depth);
    const torch::Tensor k = Intrinsics(camera).unsqueeze(0);
    const torch::Tensor warped =
        Warp(src, ProjectionGrid(depth, k,
                                 IsometryTensor(source_in_target.inverse())))
            .contiguous();
    cv::Mat out(source.rows, source.cols, CV_32F);
    std::memcpy(out.data, warped.data_ptr<float>(),
                sizeof(float) * out.total());
    return cv::Mat(out * 255.0);
  });
}

absl::StatusOr<float> ReprojectionLoss(
    const cv::Mat& target, std::span<const cv::Mat> sources,
    const cv::Mat& target_depth,
    std::span<const Eigen::Isometry3d> sources_in_target, const Camera& camera,
    bool automask, float ssim_weight) {
  if (sources.empty() || sources.size() != sources_in_target.size() ||
      target.empty() || target.channels() != 1 ||
      target_depth.type() != CV_32F || target_depth.size() != target.size() ||
      target.cols != camera.width || target.rows != camera.height) {
    return absl::InvalidArgumentError(
        "ReprojectionLoss: one pose per source, images of the camera's size");
  }
  for (const cv::Mat& s : sources) {
    if (s.size() != target.size() || s.channels() != 1) {
      return absl::InvalidArgumentError(
          "ReprojectionLoss: sources of the target's size, one channel");
    }
  }
  return Guarded<float>("reprojection", [&] {
    const torch::Tensor t = MatTensor(ToFloatImage(target));
    const torch::Tensor depth = MatTensor(target_depth);
    const torch::Tensor k = Intrinsics(camera).unsqueeze(0);
    std::vector<torch::Tensor> srcs, warped;
    for (size_t i = 0; i < sources.size(); ++i) {
      srcs.push_back(MatTensor(ToFloatImage(sources[i])));
      warped.push_back(
          Warp(srcs.back(),
               ProjectionGrid(depth, k,
                              IsometryTensor(sources_in_target[i].inverse()))));
    }
    at::Generator generator = at::make_generator<at::CPUGeneratorImpl>(0);
    return MinimumReprojection(t, warped, srcs, automask, ssim_weight,
                               generator)
        .mean()
        .item<float>();
  });
}

}  // namespace fleetmem::vo
