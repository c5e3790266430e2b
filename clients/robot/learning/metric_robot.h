// The metric head (metric_head.h) on a robot: fleetmem-robot --learn's
// default learner (learning.md design (a); docs/results.md measures it
// against the GPL head). The robot's encoder makes the fleet code (HOG by
// default), which never changes; the head is fitted every segment on the
// segment's codes, the traces replayed from the dynamic memory and the rest
// of that memory, and saved after every segment (a restart continues from
// it). R_ex (Eq. 11) comes from the head.
//
// Thread-safe: the agent may call Learn and ExternalRewards from any
// thread.
#ifndef FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_ROBOT_H_
#define FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_ROBOT_H_

#include <map>
#include <span>
#include <string>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "clients/robot/agent.h"
#include "clients/robot/encoder.h"
#include "clients/robot/learning/metric_head.h"

namespace fleetmem::robot::gpl {

class MetricRobotLearner : public Learner {
 public:
  // `encoder` (the robot's, outliving the learner) makes the codes; `domain`
  // is the robot's. `save_path`, if not empty, receives the head after
  // every segment (through a temporary file renamed into place).
  MetricRobotLearner(const Encoder* encoder, std::string domain,
                     MetricHead head, std::string save_path = "");

  // The head saved at `path` when there is one (INVALID_ARGUMENT if it was
  // made for codes of another dimension, DATA_LOSS if unreadable), a new one
  // with `options` otherwise.
  static absl::StatusOr<MetricHead> LoadOrNew(const std::string& path,
                                              int code_dimension,
                                              const MetricHeadOptions& options);

  absl::Status Learn(std::span<const Observation> segment,
                     std::span<const core::MemoryTrace> replayed,
                     std::span<const ReplayEntry> memory) override;
  absl::StatusOr<std::vector<float>> ExternalRewards(
      std::span<const std::vector<float>> codes,
      std::span<const core::Place> places,
      std::span<const ReplayEntry> memory) override;

  // What the last Learn saw.
  MetricLearnStats last() const;
  // Unit descriptors of codes under the current head.
  absl::StatusOr<std::vector<std::vector<float>>> Describe(
      std::span<const std::vector<float>> codes) const;

 private:
  int DomainId(const std::string& domain) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // The memory's traces of the encoder's dimension, as samples.
  std::vector<LearnSample> MemorySamples(std::span<const ReplayEntry> memory)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  const Encoder* encoder_;
  const std::string domain_;
  const std::string save_path_;
  mutable absl::Mutex mu_;
  MetricHead head_ ABSL_GUARDED_BY(mu_);
  std::map<std::string, int> domains_ ABSL_GUARDED_BY(mu_);
  MetricLearnStats last_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::robot::gpl

#endif  // FLEETMEM_CLIENTS_ROBOT_LEARNING_METRIC_ROBOT_H_
