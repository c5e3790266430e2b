#include "clients/robot/learning/segment_learner.h"

#include <algorithm>
#include <utility>

namespace fleetmem::robot::gpl {
namespace {

// 1 - |mean descriptor|^2: the mean squared distance of unit descriptors
// to their mean (0 when they are all the same).
float Spread(const std::vector<std::vector<float>>& descriptors) {
  if (descriptors.empty()) return 0.0f;
  std::vector<double> mean(descriptors[0].size(), 0.0);
  for (const std::vector<float>& d : descriptors)
    for (size_t c = 0; c < d.size(); ++c) mean[c] += d[c] / descriptors.size();
  double squared = 0;
  for (double m : mean) squared += m * m;
  return float(1.0 - squared);
}

}  // namespace

int DomainIds::Of(const std::string& domain) {
  return ids_.try_emplace(domain, static_cast<int>(ids_.size())).first->second;
}

void AppendSamples(std::span<const core::MemoryTrace> traces, size_t dimension,
                   DomainIds& domains, std::vector<LearnSample>& out) {
  for (const core::MemoryTrace& t : traces) {
    if (t.code.size() != dimension) continue;
    out.push_back({t.code, t.place, domains.Of(t.domain)});
  }
}

SegmentLearner::SegmentLearner(GplModel* model, SegmentLearnerOptions options)
    : model_(model), options_(std::move(options)), rng_(options_.seed) {}

absl::StatusOr<std::vector<std::vector<float>>> SegmentLearner::RememberedCodes(
    std::span<const LearnSample> samples) {
  std::vector<std::vector<float>> codes;
  codes.reserve(samples.size());
  for (const LearnSample& s : samples) codes.push_back(s.code);
  if (options_.replay_input == ReplayInput::kCode || codes.empty())
    return codes;
  return model_->Reencode(codes);
}

absl::StatusOr<SegmentLearner::Pool> SegmentLearner::BuildPool(
    std::span<const LearnSample> segment,
    std::initializer_list<std::span<const LearnSample>> remembered) {
  Pool pool;
  for (const LearnSample& x : segment) {
    pool.samples.push_back({x.place, x.domain});
    pool.codes.push_back(x.code);
  }
  std::vector<LearnSample> kept;
  for (std::span<const LearnSample> part : remembered) {
    const size_t cap = options_.max_decoded_remembered;
    if (options_.replay_input == ReplayInput::kDecoded && cap > 0 &&
        part.size() > cap) {
      kept.clear();
      for (size_t i = 0; i < cap; ++i)
        kept.push_back(part[i * part.size() / cap]);
      part = kept;
    }
    absl::StatusOr<std::vector<std::vector<float>>> codes =
        RememberedCodes(part);
    if (!codes.ok()) return codes.status();
    for (size_t i = 0; i < part.size(); ++i) {
      pool.samples.push_back({part[i].place, part[i].domain});
      pool.codes.push_back(std::move((*codes)[i]));
    }
  }
  return pool;
}

std::vector<size_t> SegmentLearner::DrawAnchors(size_t s, size_t r,
                                                size_t real_anchors,
                                                size_t replay_anchors) {
  std::vector<size_t> anchors;
  for (size_t i = 0; i < real_anchors; ++i) {
    anchors.push_back(std::uniform_int_distribution<size_t>(0, s - 1)(rng_));
  }
  for (size_t i = 0; i < replay_anchors; ++i) {
    anchors.push_back(s +
                      std::uniform_int_distribution<size_t>(0, r - 1)(rng_));
  }
  return anchors;
}

absl::Status SegmentLearner::TrainOn(
    const std::vector<TripletIndex>& triplets,
    const std::vector<std::vector<float>>& codes, SegmentLearnStats& stats) {
  CodeTriplets batch;
  for (const TripletIndex& t : triplets) {
    batch.anchors.push_back(codes[t.anchor]);
    batch.positives.push_back(codes[t.positive]);
    batch.negatives.push_back(codes[t.negative]);
  }
  absl::StatusOr<StepLosses> losses = model_->TrainPlaceHead(batch);
  if (!losses.ok()) return losses.status();
  if (stats.steps == 0) stats.first_loss = losses->loc;
  stats.last_loss = losses->loc;
  stats.steps += 1;
  stats.triplets += int(triplets.size());
  return absl::OkStatus();
}

absl::StatusOr<SegmentLearnStats> SegmentLearner::Learn(
    std::span<const LearnSample> segment, std::span<const LearnSample> replayed,
    std::span<const LearnSample> memory) {
  // The pool: segment [0, s), replayed [s, s + r), memory after.
  absl::StatusOr<Pool> built = BuildPool(segment, {replayed, memory});
  if (!built.ok()) return built.status();
  const std::vector<TripletSample>& pool = built->samples;
  const std::vector<std::vector<float>>& codes = built->codes;
  SegmentLearnStats stats;
  if (segment.empty() && replayed.empty()) return stats;
  const size_t s = segment.size(), r = replayed.size();
  const size_t replay_anchors =
      r == 0 ? 0
             : std::min<size_t>(
                   options_.batch_size,
                   size_t(options_.batch_size * options_.replay_share + 0.5));
  const size_t real_anchors = s == 0 ? 0 : options_.batch_size - replay_anchors;
  // The collapse guard: at every refresh of the descriptors the head is
  // checked; a healthy head is kept as the checkpoint, a collapsed one is
  // replaced by the last checkpoint and the segment's steps end there.
  std::string checkpoint;
  bool has_checkpoint = false;
  std::vector<std::vector<float>> descriptors;
  for (int step = 0; step < options_.steps_per_segment; ++step) {
    if (step % std::max(1, options_.mining_interval) == 0) {
      absl::StatusOr<std::vector<std::vector<float>>> d =
          model_->Describe(codes);
      if (!d.ok()) return d.status();
      descriptors = *std::move(d);
      if (options_.roll_back_collapse) {
        if (Spread(descriptors) >= options_.collapse_spread) {
          absl::StatusOr<std::string> saved = model_->SavePlaceHead();
          if (!saved.ok()) return saved.status();
          checkpoint = *std::move(saved);
          has_checkpoint = true;
        } else if (has_checkpoint) {
          if (absl::Status r = model_->RestorePlaceHead(checkpoint); !r.ok())
            return r;
          stats.rolled_back = true;
          break;
        }
        // (A head collapsed before any healthy state was seen trains on:
        // there is nothing to go back to.)
      }
    }
    const std::vector<size_t> anchors =
        DrawAnchors(s, r, real_anchors, replay_anchors);
    const std::vector<TripletIndex> triplets =
        MineTriplets(pool, anchors, descriptors, options_.mining, rng_);
    if (triplets.empty()) continue;
    if (absl::Status trained = TrainOn(triplets, codes, stats); !trained.ok()) {
      return trained;
    }
  }
  // After the segment: how far the pool's descriptors are from being one.
  absl::StatusOr<std::vector<std::vector<float>>> after =
      model_->Describe(codes);
  if (!after.ok()) return after.status();
  stats.descriptor_spread = Spread(*after);
  stats.collapsed = stats.descriptor_spread < options_.collapse_spread;
  if (stats.collapsed && options_.roll_back_collapse && has_checkpoint) {
    if (absl::Status r = model_->RestorePlaceHead(checkpoint); !r.ok())
      return r;
    stats.rolled_back = true;
    absl::StatusOr<std::vector<std::vector<float>>> restored =
        model_->Describe(codes);
    if (!restored.ok()) return restored.status();
    stats.descriptor_spread = Spread(*restored);
    stats.collapsed = stats.descriptor_spread < options_.collapse_spread;
  }
  return stats;
}

absl::Status SegmentLearner::LearnImages(std::span<const cv::Mat> images) {
  if (images.empty()) return absl::OkStatus();
  std::vector<cv::Mat> batch;
  for (int step = 0; step < options_.generative_steps_per_segment; ++step) {
    batch.clear();
    for (int i = 0; i < options_.batch_size; ++i) {
      batch.push_back(images[std::uniform_int_distribution<size_t>(
          0, images.size() - 1)(rng_)]);
    }
    absl::StatusOr<StepLosses> losses = model_->TrainGenerative(batch);
    if (!losses.ok()) return losses.status();
  }
  return absl::OkStatus();
}

absl::StatusOr<std::vector<float>> SegmentLearner::ExternalRewards(
    std::span<const LearnSample> segment, std::span<const LearnSample> memory) {
  std::vector<float> rewards(segment.size(), 0.0f);
  if (segment.empty()) return rewards;
  absl::StatusOr<Pool> built = BuildPool(segment, {memory});
  if (!built.ok()) return built.status();
  const std::vector<TripletSample>& pool = built->samples;
  const std::vector<std::vector<float>>& codes = built->codes;
  absl::StatusOr<std::vector<std::vector<float>>> descriptors =
      model_->Describe(codes);
  if (!descriptors.ok()) return descriptors.status();
  std::vector<size_t> anchors(segment.size());
  for (size_t i = 0; i < anchors.size(); ++i) anchors[i] = i;
  const std::vector<TripletIndex> triplets =
      HardestTriplets(pool, anchors, *descriptors, options_.mining);
  if (triplets.empty()) return rewards;
  CodeTriplets batch;
  for (const TripletIndex& t : triplets) {
    batch.anchors.push_back(codes[t.anchor]);
    batch.positives.push_back(codes[t.positive]);
    batch.negatives.push_back(codes[t.negative]);
  }
  absl::StatusOr<std::vector<float>> losses = model_->TripletLosses(batch);
  if (!losses.ok()) return losses.status();
  for (size_t i = 0; i < triplets.size(); ++i)
    rewards[triplets[i].anchor] = (*losses)[i];
  return rewards;
}

}  // namespace fleetmem::robot::gpl
