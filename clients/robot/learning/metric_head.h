// A learned place head on a fixed fleet code (learning.md, design (a)): a
// linear metric fitted in closed form from the samples a robot holds. The
// codes (unit length) are projected on their principal components, then
// whitened by the covariance of the differences between samples of one
// place: the directions in which a place's summer and winter codes differ
// (snow, light, foliage) are shrunk, the ones in which places differ are
// kept. The descriptor is the projected code, unit length, compared by
// cosine like the raw code.
//
// The fleet code never changes, so the fleet's memory stays valid whatever
// a robot learns; the head is the robot's own and costs d x k floats.
//
// Continual: each Learn call computes the statistics of the samples it is
// given (the segment's new samples, the replayed traces and the rest of the
// dynamic memory) and blends them into running estimates with weight
// `update_rate`, then refits. Pairs are samples within `pair_radius` of one
// another, taken across domains where a sample has a partner of another
// domain, within its own domain otherwise. What a robot can pair is what it
// remembers: a robot that replays nothing sees winter frames without their
// summer partners, and its estimate of what a season changes fades at the
// rate of `update_rate`.
//
// Before the first Learn the head is the identity (the raw code's cosine).
// Cost per Learn: O(n d^2) for n samples of dimension d, plus two
// eigendecompositions (d x d and k x k); for the 504-value HOG code and 1,500
// samples, about 0.2 s on one core.
//
// Pure: Eigen only (no torch, no I/O); not thread-safe.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_HEAD_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_HEAD_H_

#include <cstddef>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "Eigen/Dense"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "clients/robot/learning/segment_learner.h"
#include "clients/robot/learning/triplets.h"

namespace fleetmem::robot::gpl {

struct MetricHeadOptions {
  // k: principal components kept (at most the code's dimension).
  int dimension = 128;
  // Weight of one Learn call's statistics in the running estimates (1 =
  // each call refits from its samples alone).
  double update_rate = 0.5;
  // Added to the difference covariance's eigenvalues, as a share of their
  // mean, so that directions no pair varies in are not blown up.
  double ridge = 0.05;
  // Samples closer than this are pairs of one place (place units; Nordland:
  // 10 per file, 20 = the +-2 files of a correct match).
  double pair_radius = 20.0;
  // At most this many partners per sample, the nearest in place: with 1, a
  // sample's partner is the other season's frame of its own place where the
  // robot holds it (the pairs of the closed-form reference, issue 29).
  int max_partners = 1;
  // R_ex (Eq. 11): margin alpha of the triplet loss on squared distances
  // between unit descriptors, and the positive/negative radii.
  float margin = 0.3f;
  TripletMiningOptions mining;
};

struct MetricLearnStats {
  size_t samples = 0;
  size_t pairs = 0;
  // Pairs whose two samples come from different domains.
  size_t cross_domain_pairs = 0;
};

class MetricHead {
 public:
  // INVALID_ARGUMENT (from Learn/Describe) if code_dimension < 1.
  MetricHead(int code_dimension, MetricHeadOptions options);

  // Blends the statistics of `samples` into the running estimates and
  // refits. Each sample counts with its weight (negative counts as 0; a
  // pair with its first sample's). INVALID_ARGUMENT for a code of the
  // wrong dimension or when no sample has weight (nothing changes). Fewer
  // than two samples change nothing.
  absl::StatusOr<MetricLearnStats> Learn(std::span<const LearnSample> samples);

  // Unit descriptors of `codes` (dimension k once fitted, the code's
  // dimension before). INVALID_ARGUMENT for a code of the wrong dimension.
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) const;

  // R_ex of each segment sample (Eq. 11): its triplet loss against the
  // hardest positive and negative among the segment and `memory`, under the
  // current head.
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> memory) const;

  // The head's options, running estimates and fit, as bytes (a robot keeps
  // its head across restarts); Deserialize refits from the estimates.
  std::string Serialize() const;
  // DATA_LOSS for bytes that Serialize did not write (wrong magic, sizes
  // or length); INVALID_ARGUMENT for a head of another code dimension than
  // `code_dimension` (when positive).
  static absl::StatusOr<MetricHead> Deserialize(std::string_view bytes,
                                                int code_dimension = 0);

  bool fitted() const { return fitted_; }
  int code_dimension() const { return code_dimension_; }
  int descriptor_dimension() const;
  const MetricHeadOptions& options() const { return options_; }

 private:
  absl::Status CheckDimension(const std::vector<float>& code) const;
  Eigen::VectorXd Unit(const std::vector<float>& code) const;
  void Refit();

  int code_dimension_;
  MetricHeadOptions options_;
  bool fitted_ = false;
  bool has_pairs_ = false;
  // Running estimates: mean and second moment of the unit codes, and the
  // second moment of the pairs' differences.
  Eigen::VectorXd mean_;
  Eigen::MatrixXd second_moment_;
  Eigen::MatrixXd difference_moment_;
  // The fitted projection (k x d) and the centre it applies to.
  Eigen::MatrixXd projection_;
};

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_HEAD_H_
