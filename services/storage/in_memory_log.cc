#include "services/storage/in_memory_log.h"

#include <algorithm>
#include <functional>
#include <map>
#include <string>
#include <utility>
#include <variant>
#include <vector>

#include "absl/synchronization/mutex.h"

namespace fleetmem::storage {
namespace {

class InMemoryLog final : public engine::FleetLog {
 public:
  absl::StatusOr<std::vector<engine::AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const engine::LogAppend> entries,
      const engine::AppendOptions& options) override {
    std::vector<engine::AppendedEntry> appended;
    if (entries.empty()) return appended;
    absl::MutexLock lock(&mu_);
    Fleet& log = logs_[std::string(fleet_id)];
    if (options.only_first && log.last > 0) {
      return absl::FailedPreconditionError(
          "the fleet's log has entries already (nothing was appended)");
    }
    log.last = std::max(log.last, options.above);
    for (const engine::LogAppend& entry : entries) {
      log.entries[++log.last] = Own(entry.record);
      appended.push_back({log.last, false});
    }
    return appended;
  }

  absl::StatusOr<std::vector<engine::LogEntry>> Read(
      std::string_view fleet_id, uint64_t after, size_t max_entries) override {
    std::vector<engine::LogEntry> entries;
    absl::MutexLock lock(&mu_);
    auto it = logs_.find(fleet_id);
    if (it == logs_.end()) return entries;
    const auto& held = it->second.entries;
    for (auto entry = held.upper_bound(after);
         entry != held.end() && entries.size() < max_entries; ++entry) {
      entries.push_back({entry->first, std::string(), entry->second});
    }
    return entries;
  }

  absl::Status Trim(std::string_view fleet_id, uint64_t through) override {
    absl::MutexLock lock(&mu_);
    auto it = logs_.find(fleet_id);
    if (it == logs_.end()) return absl::OkStatus();
    auto& held = it->second.entries;
    held.erase(held.begin(), held.upper_bound(through));
    return absl::OkStatus();
  }

  absl::StatusOr<engine::LogBounds> Bounds(std::string_view fleet_id) override {
    absl::MutexLock lock(&mu_);
    auto it = logs_.find(fleet_id);
    if (it == logs_.end() || it->second.last == 0) return engine::LogBounds{};
    const Fleet& log = it->second;
    return engine::LogBounds{
        log.entries.empty() ? log.last + 1 : log.entries.begin()->first,
        log.last};
  }

  absl::StatusOr<std::vector<std::string>> Fleets() override {
    std::vector<std::string> fleets;
    absl::MutexLock lock(&mu_);
    for (const auto& [fleet_id, log] : logs_) {
      if (log.last > 0) fleets.push_back(fleet_id);
    }
    return fleets;
  }

 private:
  struct Fleet {
    std::map<uint64_t, engine::StoredRecord> entries;  // by sequence
    uint64_t last = 0;  // kept when every entry is trimmed
  };

  static engine::StoredRecord Own(const engine::LogRecord& record) {
    if (const auto* upload = std::get_if<engine::UploadRecord>(&record)) {
      return std::vector<core::MemoryTrace>(upload->traces.begin(),
                                            upload->traces.end());
    }
    if (const auto* call = std::get_if<engine::SampleReplayRecord>(&record)) {
      return engine::SampleReplayCall{
          std::string(call->robot_id), call->count,
          std::string(call->request_id),
          call->filter == nullptr ? core::ReadFilter() : *call->filter};
    }
    if (const auto* call = std::get_if<engine::DeleteTracesRecord>(&record)) {
      return *call;
    }
    if (const auto* call = std::get_if<engine::CreateFleetRecord>(&record)) {
      return *call;
    }
    if (const auto* call = std::get_if<engine::UpdateFleetRecord>(&record)) {
      return *call;
    }
    if (const auto* call =
            std::get_if<engine::EnforceRetentionRecord>(&record)) {
      return *call;
    }
    if (std::holds_alternative<engine::DeleteFleetRecord>(record)) {
      return engine::DeleteFleetRecord{};
    }
    if (const auto* call = std::get_if<engine::UpdateRewardsRecord>(&record)) {
      return engine::UpdateRewardsCall{std::vector<core::RewardUpdate>(
          call->updates.begin(), call->updates.end())};
    }
    return engine::ConsolidateRecord{};
  }

  absl::Mutex mu_;
  std::map<std::string, Fleet, std::less<>> logs_ ABSL_GUARDED_BY(mu_);
};

}  // namespace

std::unique_ptr<engine::FleetLog> NewInMemoryLog() {
  return std::make_unique<InMemoryLog>();
}

}  // namespace fleetmem::storage
