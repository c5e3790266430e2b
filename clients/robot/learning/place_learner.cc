#include "clients/robot/learning/place_learner.h"

#include <algorithm>
#include <utility>

#include "absl/strings/str_format.h"

namespace fleetmem::robot::gpl {
namespace {

class MetricLearner : public PlaceLearner {
 public:
  MetricLearner(int code_dimension, MetricHeadOptions options)
      : head_(code_dimension, std::move(options)) {}

  absl::StatusOr<std::string> Learn(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> replayed,
      std::span<const LearnSample> memory) override {
    std::vector<LearnSample> all(segment.begin(), segment.end());
    all.insert(all.end(), replayed.begin(), replayed.end());
    all.insert(all.end(), memory.begin(), memory.end());
    absl::StatusOr<MetricLearnStats> stats = head_.Learn(all);
    if (!stats.ok()) return stats.status();
    return absl::StrFormat("%d samples, %d pairs (%d across domains)",
                           stats->samples, stats->pairs,
                           stats->cross_domain_pairs);
  }
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> memory) override {
    return head_.ExternalRewards(segment, memory);
  }
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) override {
    return head_.Describe(codes);
  }

 private:
  MetricHead head_;
};

class GplLearner : public PlaceLearner {
 public:
  GplLearner(std::unique_ptr<GplModel> model, SegmentLearnerOptions options)
      : model_(std::move(model)), learner_(model_.get(), std::move(options)) {}

  absl::StatusOr<std::string> Learn(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> replayed,
      std::span<const LearnSample> memory) override {
    absl::StatusOr<SegmentLearnStats> stats =
        learner_.Learn(segment, replayed, memory);
    if (!stats.ok()) return stats.status();
    return absl::StrFormat(
        "%d steps, loss %.3f -> %.3f, descriptor spread %.3f%s", stats->steps,
        stats->first_loss, stats->last_loss, stats->descriptor_spread,
        stats->collapsed ? " COLLAPSED" : "");
  }
  absl::Status LearnObservations(std::span<const cv::Mat> images) override {
    return learner_.LearnImages(images);
  }
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> memory) override {
    return learner_.ExternalRewards(segment, memory);
  }
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) override {
    std::vector<std::vector<float>> out;
    for (size_t begin = 0; begin < codes.size(); begin += 1024) {
      const size_t n = std::min<size_t>(1024, codes.size() - begin);
      absl::StatusOr<std::vector<std::vector<float>>> d =
          model_->Describe(codes.subspan(begin, n));
      if (!d.ok()) return d.status();
      for (auto& row : *d) out.push_back(std::move(row));
    }
    return out;
  }

 private:
  std::unique_ptr<GplModel> model_;
  SegmentLearner learner_;
};

}  // namespace

absl::Status PlaceLearner::LearnObservations(std::span<const cv::Mat>) {
  return absl::OkStatus();
}

std::unique_ptr<PlaceLearner> NewMetricLearner(int code_dimension,
                                               MetricHeadOptions options) {
  return std::make_unique<MetricLearner>(code_dimension, std::move(options));
}

std::unique_ptr<PlaceLearner> NewGplLearner(std::unique_ptr<GplModel> model,
                                            SegmentLearnerOptions options) {
  return std::make_unique<GplLearner>(std::move(model), std::move(options));
}

}  // namespace fleetmem::robot::gpl
