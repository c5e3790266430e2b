// The GPL model on a robot: as the robot's encoder E (codes z for every
// observation, versioned by the model) and as its learner (Algorithm 3's
// inner loop: per segment, the place head learns from the segment and the
// traces replayed from the dynamic memory; R_ex comes from the model).
//
// The encoder and the learner share one model: the encoder is frozen (the
// fleet's shared encoder, learning.md), so the codes a robot uploads never
// change while its place head and decoder learn. Both lock the model, so
// the agent may call them from any thread.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_GPL_ROBOT_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_GPL_ROBOT_H_

#include <memory>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/segment_learner.h"
#include "clients/robot/sensing/encoder.h"
#include "clients/robot/sensing/learner.h"

namespace fleetmem::robot::gpl {

// A model and the lock every user of it takes.
struct SharedModel {
  absl::Mutex mu;
  std::unique_ptr<GplModel> model ABSL_PT_GUARDED_BY(mu);
};

// Loads a model file for a robot: the encoder is frozen on load (a robot
// never changes the codes of its fleet). Errors as GplModel::Load.
absl::StatusOr<std::unique_ptr<SharedModel>> LoadSharedModel(
    const std::string& path);

class GplEncoder : public Encoder {
 public:
  explicit GplEncoder(SharedModel* shared);
  const std::string& version() const override { return version_; }
  size_t dimension() const override { return dimension_; }
  // z = E(image); INVALID_ARGUMENT for an observation without an image.
  absl::StatusOr<std::vector<float>> Encode(
      const Observation& observation) const override;
  // A of R_in: a random horizontal rotation of the image for a model with
  // wrap-around (panoramas, scan images), a shift-crop otherwise.
  absl::StatusOr<Observation> Perturb(const Observation& observation,
                                      std::mt19937_64& rng) const override;

 private:
  SharedModel* shared_;
  std::string version_;
  size_t dimension_;
  bool wrap_;
};

class GplLearner : public Learner {
 public:
  // `save_path`, if not empty, receives the model after every segment
  // (Save's atomic rename).
  GplLearner(SharedModel* shared, SegmentLearnerOptions options,
             std::string save_path = "");
  // The place head learns from the traces whose codes are the model's
  // (SegmentLearner::Learn); then, when there are observations, the decoder
  // takes its generative steps on their images.
  absl::StatusOr<std::string> Learn(
      std::span<const core::MemoryTrace> segment,
      std::span<const Observation> observations,
      std::span<const core::MemoryTrace> replayed,
      std::span<const core::MemoryTrace> memory) override;
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const core::MemoryTrace> segment,
      std::span<const core::MemoryTrace> memory) override;
  // The place head's unit descriptors F(z) of codes.
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) override;
  // Steps and loss of the last segment.
  SegmentLearnStats last() const;

 private:
  SharedModel* shared_;
  std::string save_path_;
  DomainIds domains_;
  std::unique_ptr<SegmentLearner> learner_;
  SegmentLearnStats last_;
};

// Rotates an image about its vertical axis: column c moves to (c + shift)
// mod width.
cv::Mat RollColumns(const cv::Mat& image, int shift);

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_GPL_ROBOT_H_
