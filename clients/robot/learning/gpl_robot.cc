#include "clients/robot/learning/gpl_robot.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "clients/robot/rewards.h"

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

GplLearner::GplLearner(SharedModel* shared, std::string domain,
                       SegmentLearnerOptions options, std::string save_path)
    : shared_(shared),
      domain_(std::move(domain)),
      save_path_(std::move(save_path)) {
  absl::MutexLock lock(&shared_->mu);
  learner_ = std::make_unique<SegmentLearner>(shared_->model.get(),
                                              std::move(options));
}

int GplLearner::DomainId(const std::string& domain) {
  return domains_.try_emplace(domain, int(domains_.size())).first->second;
}

std::vector<LearnSample> GplLearner::MemorySamples(
    std::span<const ReplayEntry> memory) {
  std::vector<LearnSample> samples;
  samples.reserve(memory.size());
  for (const ReplayEntry& entry : memory) {
    samples.push_back(
        {entry.trace.code, entry.trace.place, DomainId(entry.trace.domain)});
  }
  return samples;
}

absl::Status GplLearner::Learn(std::span<const Observation> segment,
                               std::span<const core::MemoryTrace> replayed,
                               std::span<const ReplayEntry> memory) {
  absl::MutexLock lock(&shared_->mu);
  std::vector<cv::Mat> images;
  for (const Observation& o : segment) images.push_back(o.image);
  absl::StatusOr<std::vector<std::vector<float>>> codes =
      shared_->model->Encode(images);
  if (!codes.ok()) return codes.status();
  const int own = DomainId(domain_);
  std::vector<LearnSample> real;
  for (size_t i = 0; i < segment.size(); ++i) {
    real.push_back({std::move((*codes)[i]), segment[i].place, own});
  }
  std::vector<LearnSample> replay;
  for (const core::MemoryTrace& t : replayed) {
    if (t.code.size() != size_t(shared_->model->code_dimension())) continue;
    replay.push_back({t.code, t.place, DomainId(t.domain)});
  }
  std::vector<LearnSample> remembered = MemorySamples(memory);
  std::erase_if(remembered, [&](const LearnSample& s) {
    return s.code.size() != size_t(shared_->model->code_dimension());
  });
  absl::StatusOr<SegmentLearnStats> stats =
      learner_->Learn(real, replay, remembered);
  if (!stats.ok()) return stats.status();
  last_ = *stats;
  if (absl::Status g = learner_->LearnImages(images); !g.ok()) return g;
  if (!save_path_.empty()) return shared_->model->Save(save_path_);
  return absl::OkStatus();
}

absl::StatusOr<std::vector<float>> GplLearner::ExternalRewards(
    std::span<const std::vector<float>> codes,
    std::span<const core::Place> places, std::span<const ReplayEntry> memory) {
  absl::MutexLock lock(&shared_->mu);
  const int own = DomainId(domain_);
  std::vector<LearnSample> segment;
  for (size_t i = 0; i < codes.size() && i < places.size(); ++i) {
    segment.push_back({codes[i], places[i], own});
  }
  std::vector<LearnSample> remembered = MemorySamples(memory);
  std::erase_if(remembered, [&](const LearnSample& s) {
    return s.code.size() != size_t(shared_->model->code_dimension());
  });
  return learner_->ExternalRewards(segment, remembered);
}

SegmentLearnStats GplLearner::last() const { return last_; }

}  // namespace fleetmem::robot::gpl
