// The metric head (metric_head.h) as a robot's learner: fleetmem-robot
// --learn's default (learning.md design (a); docs/results.md measures it
// against the GPL head) and what fleetmem-eval lifelong runs for the metric
// methods. The robot's encoder makes the fleet code (HOG by default), which
// never changes; the head is fitted every segment on the segment's codes,
// the traces replayed from the dynamic memory and the rest of what the robot
// remembers, and saved after every segment (a restart continues from it).
// R_ex (Eq. 11) comes from the head.
//
// Thread-safe: the agent may call Learn and ExternalRewards from any
// thread.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_ROBOT_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_ROBOT_H_

#include <span>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "clients/robot/learning/metric_head.h"
#include "clients/robot/learning/segment_learner.h"
#include "clients/robot/sensing/learner.h"

namespace fleetmem::robot::gpl {

class MetricRobotLearner : public Learner {
 public:
  // `save_path`, if not empty, receives the head after every segment
  // (through a temporary file renamed into place). With
  // `importance_weights`, the remembered traces (replayed, M_D, recalled)
  // count with weight 1 / max(R, 0.001), normalised to mean 1 over them:
  // M_D is refreshed by a draw weighted by R (Eq. 18), and the weights undo
  // that bias in the head's statistics (docs/results.md measures it; off by
  // default).
  explicit MetricRobotLearner(MetricHead head, std::string save_path = "",
                              bool importance_weights = false);

  // The head saved at `path` when there is one (INVALID_ARGUMENT if it was
  // made for codes of another dimension, DATA_LOSS if unreadable), a new one
  // with `options` otherwise.
  static absl::StatusOr<MetricHead> LoadOrNew(const std::string& path,
                                              int code_dimension,
                                              const MetricHeadOptions& options);

  // Fits the head on every sample of the segment, the replayed traces and
  // the memory whose code has the head's dimension; reports samples and
  // pairs.
  absl::StatusOr<std::string> Learn(
      std::span<const core::MemoryTrace> segment,
      std::span<const Observation> observations,
      std::span<const core::MemoryTrace> replayed,
      std::span<const core::MemoryTrace> memory) override;
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const core::MemoryTrace> segment,
      std::span<const core::MemoryTrace> memory) override;
  // Unit descriptors of codes under the current head.
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) override;

  // What the last Learn saw.
  MetricLearnStats last() const;

 private:
  const std::string save_path_;
  const bool importance_weights_;
  mutable absl::Mutex mu_;
  MetricHead head_ ABSL_GUARDED_BY(mu_);
  DomainIds domains_ ABSL_GUARDED_BY(mu_);
  MetricLearnStats last_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_ROBOT_H_
