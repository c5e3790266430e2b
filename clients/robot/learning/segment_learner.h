// What a robot learns per segment (BioSLAM Algorithm 3, lines 3-6): the
// place head F is trained on the segment's real samples together with
// samples replayed from the dynamic memory (Eq. 19), with the triplet loss
// of Eq. 7; positives and negatives come from the segment, the replayed
// samples and the rest of the dynamic memory, by place (triplets.h).
//
// Replayed samples enter as codes. With ReplayInput::kDecoded a remembered
// code z' is first turned into a synthetic observation and encoded again,
// E(G(z')) (Eq. 20, the paper's generative replay); with kCode it enters as
// z' itself. The encoder is frozen (learning.md's fleet decision), so kCode
// is exact and kDecoded only adds the decoder's error: the evaluation
// measures both.
//
// Also the external reward R_ex (Eq. 11) of each new sample: its Eq. 7
// loss against the hardest positive and negative among the segment and the
// dynamic memory, under the current F.
//
// Not thread-safe; drives one model.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_SEGMENT_LEARNER_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_SEGMENT_LEARNER_H_

#include <cstdint>
#include <initializer_list>
#include <map>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/triplets.h"
#include "services/core/types.h"

namespace fleetmem::robot::gpl {

struct LearnSample {
  std::vector<float> code;  // z = E(q)
  core::Place place;
  int domain = 0;
  // Weight of the sample in a learner's statistics (the metric head's
  // importance weights; the GPL learner ignores it).
  double weight = 1.0;
};

// Domain names ("summer", "lidar") as the small integers LearnSample
// carries, in order of first appearance.
class DomainIds {
 public:
  int Of(const std::string& domain);

 private:
  std::map<std::string, int> ids_;
};

// Appends the traces whose codes have `dimension` values (a learner's code
// size; others come from another encoder) to `out` as samples.
void AppendSamples(std::span<const core::MemoryTrace> traces, size_t dimension,
                   DomainIds& domains, std::vector<LearnSample>& out);

enum class ReplayInput { kCode, kDecoded };

struct SegmentLearnerOptions {
  // Gradient steps on F per segment (the paper's "until converged", bounded
  // for a 2-core robot).
  int steps_per_segment = 60;
  // Triplets per step.
  int batch_size = 32;
  // Share of a step's anchors drawn from the replayed samples (when there
  // are any); the rest are the segment's real samples.
  double replay_share = 0.5;
  ReplayInput replay_input = ReplayInput::kCode;
  // Steps between refreshes of the pool's descriptors for negative mining.
  int mining_interval = 10;
  TripletMiningOptions mining;
  // Decoder/discriminator steps per segment on the segment's images
  // (LearnImages only; 0 = the decoder does not learn).
  int generative_steps_per_segment = 0;
  // A descriptor spread below this after a segment is reported as a
  // collapse (SegmentLearnStats::collapsed).
  float collapse_spread = 0.01f;
  // The collapse guard: the pool's descriptor spread is checked at every
  // refresh of the descriptors (mining_interval) and after the segment; a
  // head that falls below collapse_spread goes back to its last healthy
  // weights (the optimiser's state is kept) and the segment's steps end
  // there. A head never seen healthy trains on.
  bool roll_back_collapse = true;
  // With replay_input kDecoded, each remembered part of the pool (replayed,
  // memory) is cut to at most this many traces (every n-th, in order)
  // before it is decoded and re-encoded; 0 keeps all. Decoding the whole
  // remembered pool twice a segment was 262 of fleetmem-eval --quick's 723
  // s: its quick settings cap it (docs/results.md).
  size_t max_decoded_remembered = 0;
  uint64_t seed = 1;
};

struct SegmentLearnStats {
  int steps = 0;
  int triplets = 0;
  float first_loss = 0.0f;
  float last_loss = 0.0f;
  // After the segment (and a rollback): 1 - |mean descriptor|^2 over the
  // pool (the mean
  // squared distance of its unit descriptors to their mean; 0 when every
  // descriptor is the same). Below SegmentLearnerOptions::collapse_spread
  // the head has collapsed (loss stuck at the margin, every place alike).
  float descriptor_spread = 0.0f;
  bool collapsed = false;
  // A collapse was caught and the head rolled back to its last healthy
  // weights; descriptor_spread and collapsed describe the head kept.
  bool rolled_back = false;
};

class SegmentLearner {
 public:
  // `model` must outlive the learner; its encoder should be frozen.
  SegmentLearner(GplModel* model, SegmentLearnerOptions options);

  // Trains F on `segment` (real) and `replayed` (drawn from M_D), with
  // `memory` (the rest of M_D) as further positives and negatives. A
  // segment with no triplet (e.g. one sample) trains nothing.
  absl::StatusOr<SegmentLearnStats> Learn(std::span<const LearnSample> segment,
                                          std::span<const LearnSample> replayed,
                                          std::span<const LearnSample> memory);

  // generative_steps_per_segment decoder steps on `images` (the segment's
  // real observations), in batches of batch_size.
  absl::Status LearnImages(std::span<const cv::Mat> images);

  // R_ex of each segment sample (Eq. 11), in segment order.
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> memory);

  const SegmentLearnerOptions& options() const { return options_; }

 private:
  // Codes of remembered samples as the place head sees them (kDecoded:
  // E(G(z))).
  absl::StatusOr<std::vector<std::vector<float>>> RememberedCodes(
      std::span<const LearnSample> samples);

  // Samples and the codes the place head sees: the segment first, then each
  // remembered part in order.
  struct Pool {
    std::vector<TripletSample> samples;
    std::vector<std::vector<float>> codes;
  };
  absl::StatusOr<Pool> BuildPool(
      std::span<const LearnSample> segment,
      std::initializer_list<std::span<const LearnSample>> remembered);
  // A step's anchors: `real_anchors` of the segment's `s` samples, then
  // `replay_anchors` of the `r` replayed ones after them.
  std::vector<size_t> DrawAnchors(size_t s, size_t r, size_t real_anchors,
                                  size_t replay_anchors);
  // One training step of the place head on the mined `triplets` of
  // `codes`, counted in `stats`.
  absl::Status TrainOn(const std::vector<TripletIndex>& triplets,
                       const std::vector<std::vector<float>>& codes,
                       SegmentLearnStats& stats);

  GplModel* model_;
  SegmentLearnerOptions options_;
  std::mt19937_64 rng_;
};

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_SEGMENT_LEARNER_H_
