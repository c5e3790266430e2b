// One interface for what a robot learns per segment (BioSLAM Algorithm 3,
// lines 3-6), over two designs (learning.md, "Fleet decision"):
//
//   metric  a linear place head fitted from the replayed codes of a fixed
//           fleet code (metric_head.h); design (a).
//   gpl     the GPL place head (NetVLAD) trained by gradient steps on the
//           codes of the frozen fleet encoder (segment_learner.h).
//
// Both take the segment's new samples, the samples replayed from the
// dynamic memory and the rest of the memory; both give the external reward
// R_ex (Eq. 11) of new samples and the descriptors the map is searched with.
// Not thread-safe.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_PLACE_LEARNER_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_PLACE_LEARNER_H_

#include <memory>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/metric_head.h"
#include "clients/robot/learning/segment_learner.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot::gpl {

class PlaceLearner {
 public:
  virtual ~PlaceLearner() = default;
  // Learns from one segment; returns a one-line report (losses, pairs).
  virtual absl::StatusOr<std::string> Learn(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> replayed,
      std::span<const LearnSample> memory) = 0;
  // The segment's raw observations, for learners with a decoder (the GPL
  // learner's generative steps); the default ignores them.
  virtual absl::Status LearnObservations(std::span<const cv::Mat> images);
  // R_ex of each segment sample, in segment order.
  virtual absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const LearnSample> segment,
      std::span<const LearnSample> memory) = 0;
  // Unit descriptors of codes.
  virtual absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) = 0;
};

// Design (a): Learn fits the head on the segment, the replayed samples and
// the memory together.
std::unique_ptr<PlaceLearner> NewMetricLearner(int code_dimension,
                                               MetricHeadOptions options);

// The GPL head on `model`'s (frozen) codes, trained by SegmentLearner.
std::unique_ptr<PlaceLearner> NewGplLearner(std::unique_ptr<GplModel> model,
                                            SegmentLearnerOptions options);

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_PLACE_LEARNER_H_
