#include "clients/robot/learning/metric_robot.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "services/common/files.h"

namespace fleetmem::robot::gpl {

MetricRobotLearner::MetricRobotLearner(MetricHead head, std::string save_path,
                                       bool importance_weights)
    : save_path_(std::move(save_path)),
      importance_weights_(importance_weights),
      head_(std::move(head)) {}

absl::StatusOr<MetricHead> MetricRobotLearner::LoadOrNew(
    const std::string& path, int code_dimension,
    const MetricHeadOptions& options) {
  std::error_code ec;
  if (path.empty() || !std::filesystem::exists(path, ec)) {
    return MetricHead(code_dimension, options);
  }
  absl::StatusOr<std::string> bytes = files::ReadFile(path);
  if (!bytes.ok()) return bytes.status();
  absl::StatusOr<MetricHead> head =
      MetricHead::Deserialize(*bytes, code_dimension);
  if (!head.ok()) {
    return absl::Status(head.status().code(),
                        absl::StrCat(path, ": ", head.status().message()));
  }
  return head;
}

absl::StatusOr<std::string> MetricRobotLearner::Learn(
    std::span<const core::MemoryTrace> segment,
    std::span<const Observation> /*observations*/,
    std::span<const core::MemoryTrace> replayed,
    std::span<const core::MemoryTrace> memory) {
  absl::MutexLock lock(&mu_);
  const size_t dimension = size_t(head_.code_dimension());
  std::vector<LearnSample> samples;
  AppendSamples(segment, dimension, domains_, samples);
  const size_t own = samples.size();
  std::vector<float> rewards;
  for (auto part : {replayed, memory}) {
    AppendSamples(part, dimension, domains_, samples);
    for (const core::MemoryTrace& t : part)
      if (t.code.size() == dimension) rewards.push_back(t.reward);
  }
  if (importance_weights_ && samples.size() > own) {
    double total = 0;
    for (size_t i = own; i < samples.size(); ++i) {
      samples[i].weight = 1.0 / std::max(0.001, double(rewards[i - own]));
      total += samples[i].weight;
    }
    const double scale = double(samples.size() - own) / total;
    for (size_t i = own; i < samples.size(); ++i) samples[i].weight *= scale;
  }
  absl::StatusOr<MetricLearnStats> stats = head_.Learn(samples);
  if (!stats.ok()) return stats.status();
  last_ = *stats;
  const std::string report =
      absl::StrFormat("%d samples, %d pairs (%d across domains)",
                      stats->samples, stats->pairs, stats->cross_domain_pairs);
  if (save_path_.empty()) return report;
  // Written beside, then renamed: a crash leaves the old head or the new.
  const std::string temporary = save_path_ + ".tmp";
  if (absl::Status s = files::WriteFile(temporary, head_.Serialize());
      !s.ok()) {
    return s;
  }
  if (std::rename(temporary.c_str(), save_path_.c_str()) != 0) {
    return absl::InternalError(
        absl::StrCat("cannot rename ", temporary, " to ", save_path_));
  }
  return report;
}

absl::StatusOr<std::vector<float>> MetricRobotLearner::ExternalRewards(
    std::span<const core::MemoryTrace> segment,
    std::span<const core::MemoryTrace> memory) {
  absl::MutexLock lock(&mu_);
  const size_t dimension = size_t(head_.code_dimension());
  std::vector<LearnSample> own, remembered;
  for (const core::MemoryTrace& t : segment) {
    own.push_back({t.code, t.place, domains_.Of(t.domain)});
  }
  AppendSamples(memory, dimension, domains_, remembered);
  return head_.ExternalRewards(own, remembered);
}

MetricLearnStats MetricRobotLearner::last() const {
  absl::MutexLock lock(&mu_);
  return last_;
}

absl::StatusOr<std::vector<std::vector<float>>> MetricRobotLearner::Describe(
    std::span<const std::vector<float>> codes) {
  absl::MutexLock lock(&mu_);
  return head_.Describe(codes);
}

}  // namespace fleetmem::robot::gpl
