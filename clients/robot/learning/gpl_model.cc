// libtorch implementation of the GPL model (gpl_model.h). Every libtorch
// exception stops here and becomes a status.
#include "clients/robot/learning/gpl_model.h"

#include <torch/torch.h>

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/learning/torch_archive.h"
#include "opencv2/imgproc.hpp"

namespace fleetmem::robot::gpl {
namespace {

namespace F = torch::nn::functional;

// The file format written by Save; Load refuses any other.
constexpr int64_t kFormat = 1;
constexpr char kMagic[] = "fleetmem-gpl";

// A 3x3 (or k x k) convolution that pads the height with zeros and the width
// circularly (wrap) or with zeros, so the output keeps the input's size.
struct PaddedConvImpl : torch::nn::Module {
  PaddedConvImpl(int in, int out, int kernel, bool wrap)
      : pad(kernel / 2), wrap(wrap) {
    conv = register_module(
        "conv", torch::nn::Conv2d(torch::nn::Conv2dOptions(in, out, kernel)));
  }
  torch::Tensor forward(torch::Tensor x) {
    if (pad > 0) {
      F::PadFuncOptions width({pad, pad, 0, 0});
      if (wrap) width.mode(torch::kCircular);
      x = F::pad(x, width);
      x = F::pad(x, F::PadFuncOptions({0, 0, pad, pad}));
    }
    return conv->forward(x);
  }
  int64_t pad;
  bool wrap;
  torch::nn::Conv2d conv{nullptr};
};
TORCH_MODULE(PaddedConv);

// E: three conv + ReLU + 2x2 max-pool stages, then a 1x1 projection to the
// code's channels (no activation).
struct EncoderNetImpl : torch::nn::Module {
  EncoderNetImpl(const GplOptions& o, int code_channels) {
    const int c = o.encoder_channels;
    c1 = register_module("c1", PaddedConv(1, c / 2, 3, o.wrap_horizontal));
    c2 = register_module("c2", PaddedConv(c / 2, c, 3, o.wrap_horizontal));
    c3 = register_module("c3", PaddedConv(c, 2 * c, 3, o.wrap_horizontal));
    proj = register_module("proj", PaddedConv(2 * c, code_channels, 1, false));
  }
  torch::Tensor forward(torch::Tensor x) {
    x = F::max_pool2d(torch::relu(c1->forward(x)), F::MaxPool2dFuncOptions(2));
    x = F::max_pool2d(torch::relu(c2->forward(x)), F::MaxPool2dFuncOptions(2));
    x = F::max_pool2d(torch::relu(c3->forward(x)), F::MaxPool2dFuncOptions(2));
    return proj->forward(x);
  }
  PaddedConv c1{nullptr}, c2{nullptr}, c3{nullptr}, proj{nullptr};
};
TORCH_MODULE(EncoderNet);

// F = V(f(z)): f is two 3x3 conv + ReLU and a 1x1 conv to L features per
// cell; V is NetVLAD with K learned centres and a 1x1 soft assignment.
struct PlaceHeadImpl : torch::nn::Module {
  PlaceHeadImpl(const GplOptions& o, int code_channels) {
    const int h = o.head_channels;
    f1 = register_module("f1",
                         PaddedConv(code_channels, h, 3, o.wrap_horizontal));
    f2 = register_module("f2", PaddedConv(h, h, 3, o.wrap_horizontal));
    f3 = register_module("f3", PaddedConv(h, o.vlad_features, 1, false));
    assign = register_module(
        "assign", PaddedConv(o.vlad_features, o.vlad_clusters, 1, false));
    centres = register_parameter(
        "centres", torch::rand({o.vlad_clusters, o.vlad_features}) * 0.2 - 0.1);
  }
  // f(z): unit local features, N x L x h x w.
  torch::Tensor LocalFeatures(const torch::Tensor& z) {
    torch::Tensor x = torch::relu(f1->forward(z));
    x = torch::relu(f2->forward(x));
    return F::normalize(f3->forward(x), F::NormalizeFuncOptions().dim(1));
  }
  // NetVLAD's initialisation from data: k-means centres of local features,
  // and the soft assignment softmax_k(-alpha ||x - c_k||^2) expressed as the
  // 1x1 convolution 2 alpha c_k . x - alpha ||c_k||^2.
  void InitialiseFrom(const torch::Tensor& z, double alpha, uint64_t seed) {
    torch::NoGradGuard no_grad;
    torch::Tensor x =
        LocalFeatures(z).permute({0, 2, 3, 1}).reshape({-1, centres.size(1)});
    const int64_t k = centres.size(0);
    if (x.size(0) < k) return;
    torch::Generator gen = at::detail::createCPUGenerator(seed);
    torch::Tensor c =
        x.index_select(0, torch::randperm(x.size(0), gen).slice(0, 0, k))
            .clone();
    for (int iteration = 0; iteration < 20; ++iteration) {
      torch::Tensor nearest = torch::cdist(x, c).argmin(1);
      for (int64_t j = 0; j < k; ++j) {
        torch::Tensor members = x.index({nearest == j});
        if (members.size(0) > 0) c[j] = members.mean(0);
      }
    }
    centres.copy_(c);
    auto& conv = assign->conv;
    conv->weight.copy_((2.0 * alpha * c).reshape(conv->weight.sizes()));
    conv->bias.copy_(-alpha * c.pow(2).sum(1));
  }
  torch::Tensor forward(torch::Tensor z) {
    torch::Tensor x = LocalFeatures(z);  // N L h w
    torch::Tensor a =
        torch::softmax(assign->forward(x), 1).flatten(2);  // N K P
    torch::Tensor xf = x.flatten(2);                       // N L P
    torch::Tensor vlad = torch::bmm(a, xf.transpose(1, 2)) -
                         a.sum(2).unsqueeze(2) * centres.unsqueeze(0);  // N K L
    vlad = F::normalize(vlad, F::NormalizeFuncOptions().dim(2));
    return F::normalize(vlad.flatten(1), F::NormalizeFuncOptions().dim(1));
  }
  PaddedConv f1{nullptr}, f2{nullptr}, f3{nullptr}, assign{nullptr};
  torch::Tensor centres;
};
TORCH_MODULE(PlaceHead);

// G: conv on the code's map, then three (nearest 2x upsampling + conv)
// stages back to one channel at the input size (standardised intensities).
struct DecoderNetImpl : torch::nn::Module {
  DecoderNetImpl(const GplOptions& o, int code_channels) {
    const int c = o.encoder_channels;
    d0 = register_module(
        "d0", PaddedConv(code_channels, 2 * c, 3, o.wrap_horizontal));
    d1 = register_module("d1", PaddedConv(2 * c, c, 3, o.wrap_horizontal));
    d2 = register_module("d2", PaddedConv(c, c / 2, 3, o.wrap_horizontal));
    d3 = register_module("d3", PaddedConv(c / 2, 1, 3, o.wrap_horizontal));
  }
  static torch::Tensor Up(const torch::Tensor& x) {
    return F::interpolate(x, F::InterpolateFuncOptions()
                                 .scale_factor(std::vector<double>{2.0, 2.0})
                                 .mode(torch::kNearest));
  }
  torch::Tensor forward(torch::Tensor z) {
    torch::Tensor x = torch::relu(d0->forward(z));
    x = torch::relu(d1->forward(Up(x)));
    x = torch::relu(d2->forward(Up(x)));
    return d3->forward(Up(x));
  }
  PaddedConv d0{nullptr}, d1{nullptr}, d2{nullptr}, d3{nullptr};
};
TORCH_MODULE(DecoderNet);

// D: three stride-2 convs with leaky ReLU, then a linear logit.
struct DiscriminatorNetImpl : torch::nn::Module {
  explicit DiscriminatorNetImpl(const GplOptions& o) {
    const int c = o.encoder_channels;
    auto conv = [](int in, int out) {
      return torch::nn::Conv2d(
          torch::nn::Conv2dOptions(in, out, 4).stride(2).padding(1));
    };
    k1 = register_module("k1", conv(1, c / 2));
    k2 = register_module("k2", conv(c / 2, c));
    k3 = register_module("k3", conv(c, c));
    out = register_module(
        "out",
        torch::nn::Linear(c * (o.image_height / 8) * (o.image_width / 8), 1));
  }
  torch::Tensor forward(torch::Tensor x) {
    auto lrelu = [](const torch::Tensor& t) {
      return F::leaky_relu(t, F::LeakyReLUFuncOptions().negative_slope(0.2));
    };
    x = lrelu(k1->forward(x));
    x = lrelu(k2->forward(x));
    x = lrelu(k3->forward(x));
    return out->forward(x.flatten(1)).squeeze(1);
  }
  torch::nn::Conv2d k1{nullptr}, k2{nullptr}, k3{nullptr};
  torch::nn::Linear out{nullptr};
};
TORCH_MODULE(DiscriminatorNet);

absl::Status ValidateOptions(const GplOptions& o) {
  if (o.image_width <= 0 || o.image_height <= 0 || o.image_width % 8 != 0 ||
      o.image_height % 8 != 0) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "image size %dx%d: width and height must be positive multiples of 8",
        o.image_width, o.image_height));
  }
  const int cells = (o.image_width / 8) * (o.image_height / 8);
  if (o.code_dimension <= 0 || o.code_dimension % cells != 0) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "code dimension %d must be a positive multiple of %d (the %dx%d "
        "cells of the code's map)",
        o.code_dimension, cells, o.image_width / 8, o.image_height / 8));
  }
  if (o.encoder_channels < 2 || o.encoder_channels % 2 != 0 ||
      o.head_channels <= 0 || o.vlad_clusters <= 0 || o.vlad_features <= 0) {
    return absl::InvalidArgumentError(
        "encoder_channels (even, >= 2), head_channels, vlad_clusters and "
        "vlad_features must be positive");
  }
  if (!(o.margin > 0.0f)) {
    return absl::InvalidArgumentError("margin must be > 0");
  }
  return absl::OkStatus();
}

// The options as one double tensor (Save/Load), in this fixed order.
torch::Tensor OptionsToTensor(const GplOptions& o) {
  return torch::tensor(
      std::vector<double>{double(o.image_width), double(o.image_height),
                          double(o.code_dimension), double(o.encoder_channels),
                          double(o.head_channels), double(o.vlad_clusters),
                          double(o.vlad_features),
                          o.wrap_horizontal ? 1.0 : 0.0, double(o.margin),
                          o.head_learning_rate, o.encoder_learning_rate,
                          o.generative_learning_rate, double(o.pixel_weight),
                          double(o.seed), double(o.gan_weight)},
      torch::kFloat64);
}

absl::StatusOr<GplOptions> OptionsFromTensor(const torch::Tensor& t) {
  if (t.dim() != 1 || t.size(0) != 15 || t.scalar_type() != torch::kFloat64) {
    return absl::DataLossError("the options record has the wrong shape");
  }
  auto v = t.accessor<double, 1>();
  GplOptions o;
  o.image_width = int(v[0]);
  o.image_height = int(v[1]);
  o.code_dimension = int(v[2]);
  o.encoder_channels = int(v[3]);
  o.head_channels = int(v[4]);
  o.vlad_clusters = int(v[5]);
  o.vlad_features = int(v[6]);
  o.wrap_horizontal = v[7] != 0.0;
  o.margin = float(v[8]);
  o.head_learning_rate = v[9];
  o.encoder_learning_rate = v[10];
  o.generative_learning_rate = v[11];
  o.pixel_weight = float(v[12]);
  o.seed = uint64_t(v[13]);
  o.gan_weight = float(v[14]);
  return o;
}

template <typename T, typename Body>
absl::StatusOr<T> Guarded(const char* what, Body&& body) {
  return learning::Guarded<T>("gpl", what, std::forward<Body>(body));
}

}  // namespace

struct GplModel::Impl {
  Impl(const GplOptions& o, std::string v)
      : options(o),
        version(std::move(v)),
        code_channels(o.code_dimension /
                      ((o.image_width / 8) * (o.image_height / 8))),
        encoder(o, code_channels),
        head(o, code_channels),
        decoder(o, code_channels),
        discriminator(o),
        encoder_opt(encoder->parameters(),
                    torch::optim::AdamOptions(o.encoder_learning_rate)),
        head_opt(head->parameters(),
                 torch::optim::AdamOptions(o.head_learning_rate)),
        decoder_opt(decoder->parameters(),
                    torch::optim::AdamOptions(o.generative_learning_rate)
                        .betas({0.5, 0.999})),
        discriminator_opt(discriminator->parameters(),
                          torch::optim::AdamOptions(o.generative_learning_rate)
                              .betas({0.5, 0.999})) {}

  // Images -> N x 1 x H x W, grey, resized, each standardised to zero mean
  // and unit deviation (a black frame stays all zeros).
  // ImagesToTensor with OpenCV's and torch's exceptions as INVALID_ARGUMENT
  // (an image OpenCV cannot convert, e.g. of an unexpected depth).
  absl::StatusOr<torch::Tensor> ImagesToTensor(
      std::span<const cv::Mat> images) const {
    try {
      return ImagesToTensorUnguarded(images);
    } catch (const std::exception& e) {
      return absl::InvalidArgumentError(absl::StrCat(
          "gpl: cannot convert the images: ", learning::TorchMessage(e)));
    }
  }
  absl::StatusOr<torch::Tensor> ImagesToTensorUnguarded(
      std::span<const cv::Mat> images) const {
    const int w = options.image_width, h = options.image_height;
    torch::Tensor out = torch::empty({int64_t(images.size()), 1, h, w});
    for (size_t i = 0; i < images.size(); ++i) {
      const cv::Mat& image = images[i];
      if (image.empty()) {
        return absl::InvalidArgumentError(
            absl::StrFormat("image %d of the batch is empty", i));
      }
      cv::Mat grey;
      if (image.channels() == 3) {
        cv::cvtColor(image, grey, cv::COLOR_BGR2GRAY);
      } else if (image.channels() == 1) {
        grey = image;
      } else {
        return absl::InvalidArgumentError(absl::StrFormat(
            "image %d has %d channels (1 or 3 expected)", i, image.channels()));
      }
      cv::Mat resized;
      if (grey.cols != w || grey.rows != h) {
        cv::resize(grey, resized, cv::Size(w, h), 0, 0, cv::INTER_AREA);
      } else {
        resized = grey;
      }
      cv::Mat f;
      resized.convertTo(f, CV_32F);
      cv::Scalar mean, stddev;
      cv::meanStdDev(f, mean, stddev);
      f = (f - mean[0]) / std::max(stddev[0], 1.0);
      std::memcpy(out[i].data_ptr<float>(), f.ptr<float>(),
                  sizeof(float) * w * h);
    }
    return out;
  }

  absl::StatusOr<torch::Tensor> CodesToTensor(
      std::span<const std::vector<float>> codes) const {
    const int cw = options.image_width / 8, ch = options.image_height / 8;
    torch::Tensor out =
        torch::empty({int64_t(codes.size()), code_channels, ch, cw});
    for (size_t i = 0; i < codes.size(); ++i) {
      if (int(codes[i].size()) != options.code_dimension) {
        return absl::InvalidArgumentError(absl::StrFormat(
            "code %d has dimension %d; this model's codes have %d", i,
            codes[i].size(), options.code_dimension));
      }
      std::memcpy(out[i].data_ptr<float>(), codes[i].data(),
                  sizeof(float) * codes[i].size());
    }
    return out;
  }

  static std::vector<std::vector<float>> Rows(const torch::Tensor& t) {
    torch::Tensor c = t.flatten(1).contiguous();
    std::vector<std::vector<float>> rows(c.size(0));
    for (int64_t i = 0; i < c.size(0); ++i) {
      const float* p = c[i].data_ptr<float>();
      rows[i].assign(p, p + c.size(1));
    }
    return rows;
  }

  absl::StatusOr<torch::Tensor> TripletTensor(const CodeTriplets& b) const {
    if (b.anchors.empty() || b.anchors.size() != b.positives.size() ||
        b.anchors.size() != b.negatives.size()) {
      return absl::InvalidArgumentError(absl::StrFormat(
          "a triplet batch needs as many anchors, positives and negatives "
          "(%d, %d, %d), at least one",
          b.anchors.size(), b.positives.size(), b.negatives.size()));
    }
    std::vector<std::vector<float>> all;
    all.reserve(3 * b.anchors.size());
    all.insert(all.end(), b.anchors.begin(), b.anchors.end());
    all.insert(all.end(), b.positives.begin(), b.positives.end());
    all.insert(all.end(), b.negatives.begin(), b.negatives.end());
    return CodesToTensor(all);
  }

  // Eq. 7 per triplet from descriptors of [anchors; positives; negatives].
  torch::Tensor TripletLoss(const torch::Tensor& descriptors) const {
    auto parts = descriptors.chunk(3, 0);
    torch::Tensor ap = (parts[0] - parts[1]).pow(2).sum(1);
    torch::Tensor an = (parts[0] - parts[2]).pow(2).sum(1);
    return torch::relu(ap + options.margin - an);
  }

  // G and D on real images q with codes z = E(q) (z_graph keeps E's graph
  // for the pixel term when E trains). Returns (rec, gan_g) for G's loss and
  // steps D.
  std::pair<torch::Tensor, torch::Tensor> GenerativeLosses(
      const torch::Tensor& q, const torch::Tensor& z_graph) {
    torch::Tensor z = z_graph.detach();
    torch::Tensor fake = decoder->forward(z_graph);
    torch::Tensor pixel = (fake - q).abs().mean();
    // Eq. 9 trains G only: were E to learn from it, a constant encoder
    // would satisfy it trivially (the codes collapse).
    torch::Tensor consistency =
        (EncodeWithoutLearning(decoder->forward(z)) - z).abs().mean();
    torch::Tensor fake_logits = discriminator->forward(decoder->forward(z));
    torch::Tensor gan_g = F::binary_cross_entropy_with_logits(
        fake_logits, torch::ones_like(fake_logits));
    return {consistency + options.pixel_weight * pixel, gan_g};
  }

  // E(x) with gradients flowing to x but not into E's weights.
  torch::Tensor EncodeWithoutLearning(const torch::Tensor& x) {
    std::vector<torch::Tensor> params = encoder->parameters();
    std::vector<bool> was;
    for (torch::Tensor& p : params) {
      was.push_back(p.requires_grad());
      p.set_requires_grad(false);
    }
    torch::Tensor out = encoder->forward(x);
    for (size_t i = 0; i < params.size(); ++i)
      params[i].set_requires_grad(was[i]);
    return out;
  }

  float StepDiscriminator(const torch::Tensor& q, const torch::Tensor& z) {
    discriminator_opt.zero_grad();
    torch::Tensor real = discriminator->forward(q);
    torch::Tensor fake;
    {
      torch::NoGradGuard no_grad;
      fake = decoder->forward(z.detach());
    }
    torch::Tensor fake_logits = discriminator->forward(fake);
    torch::Tensor loss =
        F::binary_cross_entropy_with_logits(real, torch::ones_like(real)) +
        F::binary_cross_entropy_with_logits(fake_logits,
                                            torch::zeros_like(fake_logits));
    loss.backward();
    discriminator_opt.step();
    return loss.item<float>();
  }

  // Every module's weights as nested archives of `archive`.
  void WriteModules(torch::serialize::OutputArchive& archive) {
    learning::WriteModules(archive, Modules());
  }
  void ReadModules(torch::serialize::InputArchive& archive) {
    learning::ReadModules(archive, Modules());
  }
  std::vector<std::pair<std::string, torch::nn::Module*>> Modules() {
    return {{"encoder", encoder.get()},
            {"head", head.get()},
            {"decoder", decoder.get()},
            {"discriminator", discriminator.get()}};
  }

  GplOptions options;
  std::string version;
  int code_channels;
  bool encoder_frozen = false;
  EncoderNet encoder;
  PlaceHead head;
  DecoderNet decoder;
  DiscriminatorNet discriminator;
  torch::optim::Adam encoder_opt, head_opt, decoder_opt, discriminator_opt;
};

GplModel::GplModel(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
GplModel::~GplModel() = default;

absl::StatusOr<std::unique_ptr<GplModel>> GplModel::Create(
    const GplOptions& options, std::string version) {
  if (absl::Status valid = ValidateOptions(options); !valid.ok()) return valid;
  if (version.empty()) return absl::InvalidArgumentError("empty model version");
  return Guarded<std::unique_ptr<GplModel>>("create", [&] {
    torch::manual_seed(options.seed);
    return std::unique_ptr<GplModel>(
        new GplModel(std::make_unique<Impl>(options, std::move(version))));
  });
}

absl::Status GplModel::Save(const std::string& path) const {
  return learning::SaveModelArchive(
      path, kMagic, kFormat,
      [&](torch::serialize::OutputArchive& archive) {
        archive.write("version", c10::IValue(impl_->version));
        archive.write("encoder_frozen", c10::IValue(impl_->encoder_frozen));
        archive.write("options", OptionsToTensor(impl_->options));
      },
      impl_->Modules());
}

absl::StatusOr<std::unique_ptr<GplModel>> GplModel::Load(
    const std::string& path) {
  torch::serialize::InputArchive archive;
  if (absl::Status s = learning::OpenModelArchive(path, kMagic, kFormat,
                                                  "GPL model", archive);
      !s.ok()) {
    return s;
  }
  c10::IValue version, frozen;
  torch::Tensor options_tensor;
  if (!archive.try_read("version", version) || !version.isString() ||
      !archive.try_read("encoder_frozen", frozen) || !frozen.isBool() ||
      !archive.try_read("options", options_tensor)) {
    return absl::DataLossError(
        absl::StrCat(path, " lacks its version or options"));
  }
  absl::StatusOr<GplOptions> options = OptionsFromTensor(options_tensor);
  if (!options.ok()) return options.status();
  if (absl::Status valid = ValidateOptions(*options); !valid.ok()) {
    return absl::DataLossError(absl::StrCat(path, ": ", valid.message()));
  }
  absl::StatusOr<std::unique_ptr<GplModel>> model =
      Create(*options, version.toStringRef());
  if (!model.ok()) return model.status();
  try {
    (*model)->impl_->ReadModules(archive);
    if (frozen.toBool()) (*model)->FreezeEncoder();
  } catch (const std::exception& e) {
    return absl::DataLossError(absl::StrCat(
        path,
        ": the weights do not match the options: ", learning::TorchMessage(e)));
  }
  return model;
}

absl::StatusOr<std::unique_ptr<GplModel>> GplModel::Clone() const {
  std::stringstream buffer;
  absl::StatusOr<bool> saved = Guarded<bool>("clone", [&] {
    torch::serialize::OutputArchive archive;
    impl_->WriteModules(archive);
    archive.save_to(buffer);
    return true;
  });
  if (!saved.ok()) return saved.status();
  absl::StatusOr<std::unique_ptr<GplModel>> copy =
      Create(impl_->options, impl_->version);
  if (!copy.ok()) return copy.status();
  absl::StatusOr<bool> loaded = Guarded<bool>("clone", [&] {
    torch::serialize::InputArchive archive;
    archive.load_from(buffer);
    (*copy)->impl_->ReadModules(archive);
    return true;
  });
  if (!loaded.ok()) return loaded.status();
  if (impl_->encoder_frozen) (*copy)->FreezeEncoder();
  return copy;
}

absl::StatusOr<std::string> GplModel::SavePlaceHead() const {
  return Guarded<std::string>("save the place head", [&] {
    torch::serialize::OutputArchive archive;
    impl_->head->save(archive);
    std::ostringstream out;
    archive.save_to(out);
    return out.str();
  });
}

absl::Status GplModel::RestorePlaceHead(const std::string& bytes) {
  return Guarded<bool>("restore the place head",
                       [&] {
                         std::istringstream in(bytes);
                         torch::serialize::InputArchive archive;
                         archive.load_from(in);
                         impl_->head->load(archive);
                         return true;
                       })
      .status();
}

const GplOptions& GplModel::options() const { return impl_->options; }
const std::string& GplModel::version() const { return impl_->version; }
void GplModel::set_version(std::string version) {
  impl_->version = std::move(version);
}
int GplModel::code_dimension() const { return impl_->options.code_dimension; }
int GplModel::descriptor_dimension() const {
  return impl_->options.vlad_clusters * impl_->options.vlad_features;
}
bool GplModel::encoder_frozen() const { return impl_->encoder_frozen; }

int64_t GplModel::ParameterCount() const {
  int64_t n = 0;
  for (auto& [name, module] : impl_->Modules()) {
    for (const torch::Tensor& p : module->parameters()) n += p.numel();
  }
  return n;
}

void GplModel::FreezeEncoder() {
  impl_->encoder_frozen = true;
  for (torch::Tensor& p : impl_->encoder->parameters())
    p.set_requires_grad(false);
}

absl::StatusOr<std::vector<std::vector<float>>> GplModel::Encode(
    std::span<const cv::Mat> images) {
  absl::StatusOr<torch::Tensor> q = impl_->ImagesToTensor(images);
  if (!q.ok()) return q.status();
  return Guarded<std::vector<std::vector<float>>>("encode", [&] {
    torch::NoGradGuard no_grad;
    return Impl::Rows(impl_->encoder->forward(*q));
  });
}

absl::StatusOr<std::vector<std::vector<float>>> GplModel::Describe(
    std::span<const std::vector<float>> codes) {
  absl::StatusOr<torch::Tensor> z = impl_->CodesToTensor(codes);
  if (!z.ok()) return z.status();
  return Guarded<std::vector<std::vector<float>>>("describe", [&] {
    torch::NoGradGuard no_grad;
    return Impl::Rows(impl_->head->forward(*z));
  });
}

absl::StatusOr<std::vector<cv::Mat>> GplModel::Decode(
    std::span<const std::vector<float>> codes) {
  absl::StatusOr<torch::Tensor> z = impl_->CodesToTensor(codes);
  if (!z.ok()) return z.status();
  return Guarded<std::vector<cv::Mat>>("decode", [&] {
    torch::NoGradGuard no_grad;
    torch::Tensor q = impl_->decoder->forward(*z).contiguous();
    std::vector<cv::Mat> images;
    for (int64_t i = 0; i < q.size(0); ++i) {
      cv::Mat f(impl_->options.image_height, impl_->options.image_width, CV_32F,
                q[i].data_ptr<float>());
      cv::Mat out;
      f.convertTo(out, CV_8U, 48.0, 128.0);  // standardised -> 8 bit
      images.push_back(out);
    }
    return images;
  });
}

absl::StatusOr<std::vector<std::vector<float>>> GplModel::Reencode(
    std::span<const std::vector<float>> codes) {
  absl::StatusOr<torch::Tensor> z = impl_->CodesToTensor(codes);
  if (!z.ok()) return z.status();
  return Guarded<std::vector<std::vector<float>>>("reencode", [&] {
    torch::NoGradGuard no_grad;
    return Impl::Rows(impl_->encoder->forward(impl_->decoder->forward(*z)));
  });
}

absl::Status GplModel::InitialisePlaceHead(
    std::span<const std::vector<float>> codes) {
  absl::StatusOr<torch::Tensor> z = impl_->CodesToTensor(codes);
  if (!z.ok()) return z.status();
  return Guarded<bool>("initialise place head",
                       [&] {
                         impl_->head->InitialiseFrom(*z, 10.0,
                                                     impl_->options.seed);
                         return true;
                       })
      .status();
}

absl::StatusOr<std::vector<float>> GplModel::TripletLosses(
    const CodeTriplets& batch) {
  absl::StatusOr<torch::Tensor> z = impl_->TripletTensor(batch);
  if (!z.ok()) return z.status();
  return Guarded<std::vector<float>>("triplet losses", [&] {
    torch::NoGradGuard no_grad;
    torch::Tensor loss =
        impl_->TripletLoss(impl_->head->forward(*z)).contiguous();
    const float* p = loss.data_ptr<float>();
    return std::vector<float>(p, p + loss.size(0));
  });
}

absl::StatusOr<StepLosses> GplModel::TrainPlaceHead(const CodeTriplets& batch) {
  absl::StatusOr<torch::Tensor> z = impl_->TripletTensor(batch);
  if (!z.ok()) return z.status();
  return Guarded<StepLosses>("train place head", [&] {
    impl_->head_opt.zero_grad();
    torch::Tensor loss = impl_->TripletLoss(impl_->head->forward(*z)).mean();
    loss.backward();
    impl_->head_opt.step();
    StepLosses out;
    out.loc = loss.item<float>();
    return out;
  });
}

absl::StatusOr<StepLosses> GplModel::TrainGenerative(
    std::span<const cv::Mat> images) {
  absl::StatusOr<torch::Tensor> q = impl_->ImagesToTensor(images);
  if (!q.ok()) return q.status();
  if (images.empty())
    return absl::InvalidArgumentError("no images to train on");
  return Guarded<StepLosses>("train decoder", [&] {
    torch::Tensor z;
    {
      torch::NoGradGuard no_grad;
      z = impl_->encoder->forward(*q);
    }
    impl_->decoder_opt.zero_grad();
    auto [rec, gan_g] = impl_->GenerativeLosses(*q, z);
    (rec + options().gan_weight * gan_g).backward();
    impl_->decoder_opt.step();
    StepLosses out;
    out.rec = rec.item<float>();
    out.gan_g = gan_g.item<float>();
    out.gan_d = impl_->StepDiscriminator(*q, z);
    return out;
  });
}

absl::StatusOr<StepLosses> GplModel::TrainJoint(const ImageTriplets& batch) {
  if (impl_->encoder_frozen) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the encoder of ", impl_->version, " is frozen; train the place head"));
  }
  if (batch.anchors.empty() || batch.anchors.size() != batch.positives.size() ||
      batch.anchors.size() != batch.negatives.size()) {
    return absl::InvalidArgumentError(
        "a triplet batch needs as many anchors, positives and negatives");
  }
  std::vector<cv::Mat> all(batch.anchors);
  all.insert(all.end(), batch.positives.begin(), batch.positives.end());
  all.insert(all.end(), batch.negatives.begin(), batch.negatives.end());
  absl::StatusOr<torch::Tensor> q = impl_->ImagesToTensor(all);
  if (!q.ok()) return q.status();
  return Guarded<StepLosses>("train joint", [&] {
    impl_->encoder_opt.zero_grad();
    impl_->head_opt.zero_grad();
    impl_->decoder_opt.zero_grad();
    torch::Tensor z = impl_->encoder->forward(*q);
    torch::Tensor loc = impl_->TripletLoss(impl_->head->forward(z)).mean();
    auto [rec, gan_g] = impl_->GenerativeLosses(*q, z);
    (loc + rec + options().gan_weight * gan_g).backward();  // Eq. 10
    impl_->encoder_opt.step();
    impl_->head_opt.step();
    impl_->decoder_opt.step();
    StepLosses out;
    out.loc = loc.item<float>();
    out.rec = rec.item<float>();
    out.gan_g = gan_g.item<float>();
    out.gan_d = impl_->StepDiscriminator(*q, z);
    return out;
  });
}

void SetTorchThreads(int threads) { torch::set_num_threads(threads); }

}  // namespace fleetmem::robot::gpl
