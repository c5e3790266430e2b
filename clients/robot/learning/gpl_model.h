// The General Place Learning (GPL) model of BioSLAM (Sec. IV; learning.md
// "GPL model"), in libtorch on the CPU. libtorch stays behind this header:
// callers see codes and descriptors as float vectors and images as cv::Mat.
//
//   E  encoder        image q (1 x H x W, grey, standardised)  -> code z
//                     (C x H/8 x W/8 = dimension D; 256 by default)
//   F  place head     F(q) = V(f(z)): a convolution stage f on the code's
//                     map, then NetVLAD V (K clusters of L features),
//                     intra- and L2-normalised (K * L values)
//   G  decoder        z -> synthetic observation q^ (Eq. 20)
//   D  discriminator  q -> logit "real" (Eq. 6)
//
// Losses: the triplet loss of Eq. 7 (margin alpha, squared descriptor
// distances) over real and replayed samples; L_rec of Eq. 9,
// ||E(G(z')) - z'|| (mean absolute error), plus a pixel reconstruction
// ||G(E(q)) - q|| that keeps the decoder anchored to real images (our
// addition, weight `pixel_weight`); L_gan of Eq. 6 (non-saturating for G).
// L_joint = L_loc + L_rec + L_gan (Eq. 10).
//
// Fleet decision (learning.md): the encoder E is trained once (TrainJoint on
// an initial domain) and then frozen; its version names the weights it was
// frozen with, and travels with every code. The place head, decoder and
// discriminator keep learning (TrainPlaceHead, TrainGenerative).
//
// Horizontal wrap-around (options.wrap_horizontal): every convolution pads the
// width circularly, so panoramas and scan images keep their features under a
// rotation about the vertical axis.
//
// Not thread-safe: one thread drives a model. Every computation runs with
// the number of intra-op threads torch was given (set_num_threads).
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_GPL_MODEL_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_GPL_MODEL_H_

#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot::gpl {

struct GplOptions {
  // Input size: every image is converted to grey and resized to this
  // (Nordland's frames are 64 x 32). Both must be multiples of 8.
  int image_width = 64;
  int image_height = 32;
  // D, the memory code's dimension; a multiple of (width/8)*(height/8).
  int code_dimension = 256;
  // Channels of the three encoder stages.
  int encoder_channels = 32;
  // Channels of the place head's convolution stage f.
  int head_channels = 64;
  // NetVLAD: K clusters of L-dimensional local features (SphereVLAD's 32
  // of 16; learning.md).
  int vlad_clusters = 32;
  int vlad_features = 16;
  // Circular padding along the width (panoramas, scans).
  bool wrap_horizontal = false;
  // alpha of Eq. 7, on squared distances between unit descriptors (0..4).
  float margin = 0.3f;
  // Adam learning rates: place head (f, V), encoder, decoder/discriminator.
  double head_learning_rate = 3e-4;
  double encoder_learning_rate = 1e-3;
  double generative_learning_rate = 1e-3;
  // Weight of the pixel reconstruction term in the decoder's loss.
  float pixel_weight = 1.0f;
  // Weight of L_gan for the decoder in L_joint (Eq. 10 has 1).
  float gan_weight = 1.0f;
  // Seeds torch's generator when the model is created (initial weights).
  uint64_t seed = 1;
};

// One training batch of triplets (Eq. 7): row i is (anchor, positive,
// negative) codes, each of dimension D.
struct CodeTriplets {
  std::vector<std::vector<float>> anchors;
  std::vector<std::vector<float>> positives;
  std::vector<std::vector<float>> negatives;
};

// The same with images (used while the encoder trains, TrainJoint).
struct ImageTriplets {
  std::vector<cv::Mat> anchors;
  std::vector<cv::Mat> positives;
  std::vector<cv::Mat> negatives;
};

struct StepLosses {
  float loc = 0.0f;    // mean triplet loss (Eq. 7)
  float rec = 0.0f;    // Eq. 9 (+ pixel term)
  float gan_g = 0.0f;  // G's adversarial loss
  float gan_d = 0.0f;  // D's loss
};

class GplModel {
 public:
  // A new model with seeded random weights, encoder version `version`
  // (e.g. "gpl-64x32-d256-v1"). INVALID_ARGUMENT for inconsistent options.
  static absl::StatusOr<std::unique_ptr<GplModel>> Create(
      const GplOptions& options, std::string version);
  // Weights and options saved by Save. NOT_FOUND / DATA_LOSS (unreadable or
  // not a GPL file) / FAILED_PRECONDITION (saved by an incompatible format).
  static absl::StatusOr<std::unique_ptr<GplModel>> Load(
      const std::string& path);
  ~GplModel();
  GplModel(const GplModel&) = delete;
  GplModel& operator=(const GplModel&) = delete;

  // Writes options, version and every module's weights to `path` (through a
  // temporary file renamed into place). INTERNAL on an I/O error.
  absl::Status Save(const std::string& path) const;
  // A deep copy (weights, optimiser state not included).
  absl::StatusOr<std::unique_ptr<GplModel>> Clone() const;
  // The place head's weights as bytes, and back (a learner's checkpoint:
  // SegmentLearner rolls a collapsed head back). The optimiser's state is
  // not included. INTERNAL / DATA_LOSS from torch's serialisation.
  absl::StatusOr<std::string> SavePlaceHead() const;
  absl::Status RestorePlaceHead(const std::string& bytes);

  const GplOptions& options() const;
  // The encoder's version, carried by every code.
  const std::string& version() const;
  void set_version(std::string version);
  int code_dimension() const;
  int descriptor_dimension() const;
  int64_t ParameterCount() const;
  bool encoder_frozen() const;
  // Freezes E (no more gradient steps on it).
  void FreezeEncoder();

  // z = E(q) for each image (any size, 1 or 3 channels, 8-bit).
  // INVALID_ARGUMENT for an empty image.
  absl::StatusOr<std::vector<std::vector<float>>> Encode(
      std::span<const cv::Mat> images);
  // F descriptors of codes (unit length). INVALID_ARGUMENT for a code of the
  // wrong dimension.
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes);
  // q^ = G(z), as 8-bit grey images of the model's input size.
  absl::StatusOr<std::vector<cv::Mat>> Decode(
      std::span<const std::vector<float>> codes);
  // E(G(z)): a code passed through the decoder and back (replay input).
  absl::StatusOr<std::vector<std::vector<float>>> Reencode(
      std::span<const std::vector<float>> codes);

  // NetVLAD's data-driven initialisation (Arandjelovic et al.): k-means of
  // the local features of `codes` give the centres and a sharp soft
  // assignment (alpha = 10). A random head maps every input to nearly the
  // same descriptor; call this once on codes of the first domain.
  absl::Status InitialisePlaceHead(std::span<const std::vector<float>> codes);

  // Per-triplet losses max(d(a,p)^2 + alpha - d(a,n)^2, 0) under F, without
  // a gradient step (R_ex, Eq. 11).
  absl::StatusOr<std::vector<float>> TripletLosses(const CodeTriplets& batch);

  // One Adam step of L_loc on the place head (E untouched).
  absl::StatusOr<StepLosses> TrainPlaceHead(const CodeTriplets& batch);
  // One step of the decoder and discriminator on real images (L_rec + L_gan;
  // E untouched).
  absl::StatusOr<StepLosses> TrainGenerative(std::span<const cv::Mat> images);
  // One step of L_joint (Eq. 10) on E, F, G and D together. FAILED_PRECONDITION
  // once the encoder is frozen.
  absl::StatusOr<StepLosses> TrainJoint(const ImageTriplets& batch);

 private:
  struct Impl;
  explicit GplModel(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

// Sets torch's intra-op threads (the robot's and the eval's CPU budget).
void SetTorchThreads(int threads);

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_GPL_MODEL_H_
