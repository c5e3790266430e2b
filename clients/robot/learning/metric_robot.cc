#include "clients/robot/learning/metric_robot.h"

#include <cstdio>
#include <filesystem>
#include <utility>

#include "absl/strings/str_cat.h"
#include "services/common/files.h"

namespace fleetmem::robot::gpl {

MetricRobotLearner::MetricRobotLearner(const Encoder* encoder,
                                       std::string domain, MetricHead head,
                                       std::string save_path)
    : encoder_(encoder),
      domain_(std::move(domain)),
      save_path_(std::move(save_path)),
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

int MetricRobotLearner::DomainId(const std::string& domain) {
  return domains_.try_emplace(domain, int(domains_.size())).first->second;
}

std::vector<LearnSample> MetricRobotLearner::MemorySamples(
    std::span<const ReplayEntry> memory) {
  std::vector<LearnSample> samples;
  for (const ReplayEntry& e : memory) {
    if (int(e.trace.code.size()) != head_.code_dimension()) continue;
    samples.push_back({e.trace.code, e.trace.place, DomainId(e.trace.domain)});
  }
  return samples;
}

absl::Status MetricRobotLearner::Learn(
    std::span<const Observation> segment,
    std::span<const core::MemoryTrace> replayed,
    std::span<const ReplayEntry> memory) {
  std::vector<LearnSample> samples;
  for (const Observation& o : segment) {
    absl::StatusOr<std::vector<float>> code = encoder_->Encode(o);
    if (!code.ok()) return code.status();
    samples.push_back({*std::move(code), o.place, 0});
  }
  absl::MutexLock lock(&mu_);
  const int own = DomainId(domain_);
  for (LearnSample& s : samples) s.domain = own;
  for (const core::MemoryTrace& t : replayed) {
    if (int(t.code.size()) != head_.code_dimension()) continue;
    samples.push_back({t.code, t.place, DomainId(t.domain)});
  }
  for (LearnSample& s : MemorySamples(memory)) samples.push_back(std::move(s));
  absl::StatusOr<MetricLearnStats> stats = head_.Learn(samples);
  if (!stats.ok()) return stats.status();
  last_ = *stats;
  if (save_path_.empty()) return absl::OkStatus();
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
  return absl::OkStatus();
}

absl::StatusOr<std::vector<float>> MetricRobotLearner::ExternalRewards(
    std::span<const std::vector<float>> codes,
    std::span<const core::Place> places, std::span<const ReplayEntry> memory) {
  absl::MutexLock lock(&mu_);
  const int own = DomainId(domain_);
  std::vector<LearnSample> segment;
  for (size_t i = 0; i < codes.size() && i < places.size(); ++i)
    segment.push_back({codes[i], places[i], own});
  return head_.ExternalRewards(segment, MemorySamples(memory));
}

MetricLearnStats MetricRobotLearner::last() const {
  absl::MutexLock lock(&mu_);
  return last_;
}

absl::StatusOr<std::vector<std::vector<float>>> MetricRobotLearner::Describe(
    std::span<const std::vector<float>> codes) const {
  absl::MutexLock lock(&mu_);
  return head_.Describe(codes);
}

}  // namespace fleetmem::robot::gpl
