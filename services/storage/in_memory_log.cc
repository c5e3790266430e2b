#include "services/storage/in_memory_log.h"

#include <functional>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include "absl/synchronization/mutex.h"

namespace fleetmem::storage {
namespace {

class InMemoryLog final : public engine::FleetLog {
 public:
  absl::Status Append(std::string_view fleet_id,
                      std::span<const engine::LogAppend> entries) override {
    absl::MutexLock lock(&mu_);
    auto& log = logs_[std::string(fleet_id)];
    for (const engine::LogAppend& entry : entries) {
      log[entry.sequence] = std::vector<core::MemoryTrace>(entry.traces.begin(),
                                                           entry.traces.end());
    }
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<engine::LoggedUpload>> Read(
      std::string_view fleet_id, uint64_t after, size_t max_entries) override {
    std::vector<engine::LoggedUpload> entries;
    absl::MutexLock lock(&mu_);
    auto it = logs_.find(fleet_id);
    if (it == logs_.end()) return entries;
    for (auto entry = it->second.upper_bound(after);
         entry != it->second.end() && entries.size() < max_entries; ++entry) {
      entries.push_back({entry->first, entry->second});
    }
    return entries;
  }

  absl::Status Trim(std::string_view fleet_id, uint64_t through) override {
    absl::MutexLock lock(&mu_);
    auto it = logs_.find(fleet_id);
    if (it == logs_.end()) return absl::OkStatus();
    auto& log = it->second;
    log.erase(log.begin(), log.upper_bound(through));
    if (log.empty()) logs_.erase(it);
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<std::pair<std::string, uint64_t>>> Tails()
      override {
    std::vector<std::pair<std::string, uint64_t>> tails;
    absl::MutexLock lock(&mu_);
    for (const auto& [fleet_id, log] : logs_) {
      if (!log.empty()) tails.emplace_back(fleet_id, log.rbegin()->first);
    }
    return tails;
  }

 private:
  absl::Mutex mu_;
  // By fleet id, then sequence.
  std::map<std::string, std::map<uint64_t, std::vector<core::MemoryTrace>>,
           std::less<>>
      logs_ ABSL_GUARDED_BY(mu_);
};

}  // namespace

std::unique_ptr<engine::FleetLog> NewInMemoryLog() {
  return std::make_unique<InMemoryLog>();
}

}  // namespace fleetmem::storage
