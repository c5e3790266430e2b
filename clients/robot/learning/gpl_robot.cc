#include "clients/robot/learning/gpl_robot.h"

#include <algorithm>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "clients/robot/sensing/rewards.h"

namespace fleetmem::robot::gpl {

absl::StatusOr<std::unique_ptr<SharedModel>> LoadSharedModel(
    const std::string& path) {
  absl::StatusOr<std::unique_ptr<GplModel>> model = GplModel::Load(path);
  if (!model.ok()) return model.status();
  (*model)->FreezeEncoder();
  auto shared = std::make_unique<SharedModel>();
  absl::MutexLock lock(&shared->mu);
  shared->model = *std::move(model);
  return shared;
}

cv::Mat RollColumns(const cv::Mat& image, int shift) {
  if (image.empty()) return image;
  const int w = image.cols;
  shift = ((shift % w) + w) % w;
  cv::Mat out(image.size(), image.type());
  if (shift == 0) {
    image.copyTo(out);
    return out;
  }
  image.colRange(0, w - shift).copyTo(out.colRange(shift, w));
  image.colRange(w - shift, w).copyTo(out.colRange(0, shift));
  return out;
}

GplEncoder::GplEncoder(SharedModel* shared) : shared_(shared) {
  absl::MutexLock lock(&shared_->mu);
  version_ = shared_->model->version();
  dimension_ = shared_->model->code_dimension();
  wrap_ = shared_->model->options().wrap_horizontal;
}

absl::StatusOr<std::vector<float>> GplEncoder::Encode(
    const Observation& observation) const {
  if (observation.image.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "observation ", observation.name, " has no image (the GPL model ",
        version_, " encodes images)"));
  }
  absl::MutexLock lock(&shared_->mu);
  absl::StatusOr<std::vector<std::vector<float>>> codes =
      shared_->model->Encode(std::span<const cv::Mat>(&observation.image, 1));
  if (!codes.ok()) return codes.status();
  return std::move((*codes)[0]);
}

absl::StatusOr<Observation> GplEncoder::Perturb(const Observation& observation,
                                                std::mt19937_64& rng) const {
  Observation perturbed = observation;
  if (wrap_) {
    perturbed.image = RollColumns(
        observation.image,
        std::uniform_int_distribution<int>(1, observation.image.cols - 1)(rng));
    return perturbed;
  }
  absl::StatusOr<cv::Mat> moved =
      RandomShiftCrop(observation.image, ShiftCropOptions{}, rng);
  if (!moved.ok()) return moved.status();
  perturbed.image = *std::move(moved);
  return perturbed;
}

GplLearner::GplLearner(SharedModel* shared, SegmentLearnerOptions options,
                       std::string save_path)
    : shared_(shared), save_path_(std::move(save_path)) {
  absl::MutexLock lock(&shared_->mu);
  learner_ = std::make_unique<SegmentLearner>(shared_->model.get(),
                                              std::move(options));
}

absl::StatusOr<std::string> GplLearner::Learn(
    std::span<const core::MemoryTrace> segment,
    std::span<const Observation> observations,
    std::span<const core::MemoryTrace> replayed,
    std::span<const core::MemoryTrace> memory) {
  absl::MutexLock lock(&shared_->mu);
  const size_t dimension = size_t(shared_->model->code_dimension());
  std::vector<LearnSample> real, replay, remembered;
  AppendSamples(segment, dimension, domains_, real);
  AppendSamples(replayed, dimension, domains_, replay);
  AppendSamples(memory, dimension, domains_, remembered);
  absl::StatusOr<SegmentLearnStats> stats =
      learner_->Learn(real, replay, remembered);
  if (!stats.ok()) return stats.status();
  last_ = *stats;
  if (!observations.empty()) {
    std::vector<cv::Mat> images;
    for (const Observation& o : observations) images.push_back(o.image);
    if (absl::Status g = learner_->LearnImages(images); !g.ok()) return g;
  }
  if (!save_path_.empty()) {
    if (absl::Status s = shared_->model->Save(save_path_); !s.ok()) return s;
  }
  return absl::StrFormat(
      "%d steps, loss %.3f -> %.3f, descriptor spread %.3f%s", stats->steps,
      stats->first_loss, stats->last_loss, stats->descriptor_spread,
      stats->rolled_back ? " COLLAPSED, rolled back"
      : stats->collapsed ? " COLLAPSED"
                         : "");
}

absl::StatusOr<std::vector<float>> GplLearner::ExternalRewards(
    std::span<const core::MemoryTrace> segment,
    std::span<const core::MemoryTrace> memory) {
  absl::MutexLock lock(&shared_->mu);
  std::vector<LearnSample> own, remembered;
  for (const core::MemoryTrace& t : segment) {
    own.push_back({t.code, t.place, domains_.Of(t.domain)});
  }
  AppendSamples(memory, size_t(shared_->model->code_dimension()), domains_,
                remembered);
  return learner_->ExternalRewards(own, remembered);
}

absl::StatusOr<std::vector<std::vector<float>>> GplLearner::Describe(
    std::span<const std::vector<float>> codes) {
  absl::MutexLock lock(&shared_->mu);
  std::vector<std::vector<float>> out;
  for (size_t begin = 0; begin < codes.size(); begin += 1024) {
    const size_t n = std::min<size_t>(1024, codes.size() - begin);
    absl::StatusOr<std::vector<std::vector<float>>> d =
        shared_->model->Describe(codes.subspan(begin, n));
    if (!d.ok()) return d.status();
    for (auto& row : *d) out.push_back(std::move(row));
  }
  return out;
}

SegmentLearnStats GplLearner::last() const { return last_; }

}  // namespace fleetmem::robot::gpl
