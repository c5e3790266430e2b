#include "services/storage/in_memory_store.h"

#include <algorithm>
#include <functional>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "services/storage/mutation_checks.h"

namespace fleetmem::storage {
namespace {

using core::TraceKey;

struct StoredCluster {
  std::string robot_id;
  std::vector<float> centroid;
  std::vector<TraceKey> members;
};

struct Fleet {
  std::optional<engine::FleetMeta> meta;
  std::map<TraceKey, core::MemoryTrace> pending;
  std::map<uint64_t, StoredCluster> clusters;
  std::map<TraceKey, core::MemoryTrace> traces;  // of the static memory
  std::map<std::string, engine::RobotRecord> robots;
  std::map<uint64_t, core::MemoryEvent> events;

  bool empty() const {
    return !meta && pending.empty() && clusters.empty() && traces.empty() &&
           robots.empty() && events.empty();
  }

  void DropMember(uint64_t cluster_id, const TraceKey& key) {
    auto cluster = clusters.find(cluster_id);
    if (cluster == clusters.end()) return;
    std::erase(cluster->second.members, key);
  }

  void EraseCluster(uint64_t id) {
    auto cluster = clusters.find(id);
    if (cluster == clusters.end()) return;
    for (const TraceKey& member : cluster->second.members) traces.erase(member);
    clusters.erase(cluster);
  }

  void EraseTrace(const TraceKey& key) {
    auto trace = traces.find(key);
    if (trace == traces.end()) return;
    DropMember(trace->second.cluster_id, key);
    traces.erase(trace);
  }

  // The codes of the put clusters' traces that come without one, as held
  // before `m` (a merge's survivor may take the traces of a cluster that
  // `m` erases first); INVALID_ARGUMENT if a trace has none held.
  absl::StatusOr<std::map<TraceKey, std::vector<float>>> KeptCodes(
      const engine::FleetMutation& m) const {
    std::map<TraceKey, std::vector<float>> codes;
    for (const core::Cluster& cluster : m.put_clusters) {
      for (const core::MemoryTrace& trace : cluster.traces) {
        if (!trace.code.empty()) continue;
        auto held = traces.find(trace.key());
        if (held == traces.end()) {
          return internal::NoStoredCode(trace, cluster.id);
        }
        codes[trace.key()] = held->second.code;
      }
    }
    return codes;
  }

  void PutCluster(const core::Cluster& cluster,
                  std::map<TraceKey, std::vector<float>>& kept_codes) {
    std::set<TraceKey> keep;
    for (const core::MemoryTrace& trace : cluster.traces) {
      keep.insert(trace.key());
    }
    if (auto old = clusters.find(cluster.id); old != clusters.end()) {
      for (const TraceKey& member : old->second.members) {
        if (!keep.contains(member)) traces.erase(member);
      }
    }
    StoredCluster stored{cluster.robot_id, cluster.centroid, {}};
    for (const core::MemoryTrace& trace : cluster.traces) {
      auto existing = traces.find(trace.key());
      if (existing != traces.end() &&
          existing->second.cluster_id != cluster.id) {
        DropMember(existing->second.cluster_id, trace.key());
      }
      core::MemoryTrace& slot = traces[trace.key()];
      slot = trace;
      slot.cluster_id = cluster.id;
      if (slot.code.empty()) slot.code = std::move(kept_codes[trace.key()]);
      stored.members.push_back(trace.key());
    }
    clusters[cluster.id] = std::move(stored);
  }

  void UpdateTrace(const core::MemoryTrace& trace) {
    auto existing = traces.find(trace.key());
    if (existing == traces.end()) return;
    const uint64_t cluster_id = existing->second.cluster_id;
    std::vector<float> code = std::move(existing->second.code);
    existing->second = trace;
    existing->second.cluster_id = cluster_id;
    existing->second.code = std::move(code);  // an update keeps the code
  }
};

class InMemoryStore final : public engine::MemoryStore {
 public:
  absl::StatusOr<std::vector<std::string>> ListFleets() override {
    absl::MutexLock lock(&mu_);
    std::vector<std::string> ids;
    ids.reserve(fleets_.size());
    for (const auto& [id, fleet] : fleets_) ids.push_back(id);
    return ids;
  }

  absl::StatusOr<engine::FleetRecord> LoadFleet(
      std::string_view fleet_id) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    engine::FleetRecord record;
    record.fleet_id = std::string(fleet_id);
    absl::MutexLock lock(&mu_);
    auto it = fleets_.find(fleet_id);
    if (it == fleets_.end()) return record;
    const Fleet& fleet = it->second;
    record.meta = fleet.meta.value_or(engine::FleetMeta{});
    for (const auto& [key, trace] : fleet.pending) {
      record.pending.push_back(trace);
    }
    for (const auto& [id, stored] : fleet.clusters) {
      core::Cluster& cluster = record.clusters.emplace_back();
      cluster.id = id;
      cluster.robot_id = stored.robot_id;
      cluster.centroid = stored.centroid;
      for (const TraceKey& member : stored.members) {
        cluster.traces.push_back(fleet.traces.at(member));
      }
    }
    for (const auto& [id, robot] : fleet.robots) record.robots.push_back(robot);
    return record;
  }

  absl::StatusOr<engine::FleetRecord> LoadFleetWithoutClusters(
      std::string_view fleet_id) override {
    absl::StatusOr<engine::FleetRecord> record = LoadFleet(fleet_id);
    if (record.ok()) record->clusters.clear();
    return record;
  }

  // Everything is in memory: the codes are copied, then the held ones
  // dropped (outside the lock: the function may wait).
  absl::StatusOr<engine::FleetRecord> LoadFleetWithoutHeldCodes(
      std::string_view fleet_id,
      const std::function<bool(const TraceKey&)>& code_held_elsewhere)
      override {
    absl::StatusOr<engine::FleetRecord> record = LoadFleet(fleet_id);
    if (!record.ok() || !code_held_elsewhere) return record;
    for (core::Cluster& cluster : record->clusters) {
      for (core::MemoryTrace& trace : cluster.traces) {
        if (code_held_elsewhere(trace.key())) {
          std::vector<float>().swap(trace.code);
        }
      }
    }
    return record;
  }

  absl::Status Apply(std::string_view fleet_id,
                     const engine::FleetMutation& m) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    if (absl::Status status = internal::CheckMutation(m); !status.ok()) {
      return status;
    }
    absl::MutexLock lock(&mu_);
    auto it = fleets_.try_emplace(std::string(fleet_id)).first;
    Fleet& fleet = it->second;
    absl::StatusOr<std::map<TraceKey, std::vector<float>>> kept_codes =
        fleet.KeptCodes(m);
    if (!kept_codes.ok()) {
      if (fleet.empty()) fleets_.erase(it);
      return kept_codes.status();
    }
    ++writes_[std::string(fleet_id)];
    for (const TraceKey& key : m.erase_pending) fleet.pending.erase(key);
    for (uint64_t id : m.erase_clusters) fleet.EraseCluster(id);
    for (const TraceKey& key : m.erase_traces) fleet.EraseTrace(key);
    if (m.put_meta) fleet.meta = m.meta;
    for (const core::MemoryTrace& trace : m.put_pending) {
      fleet.pending[trace.key()] = trace;
    }
    for (const core::Cluster& cluster : m.put_clusters) {
      fleet.PutCluster(cluster, *kept_codes);
    }
    for (const core::MemoryTrace& trace : m.update_traces) {
      fleet.UpdateTrace(trace);
    }
    for (const engine::RobotRecord& robot : m.put_robots) {
      fleet.robots[robot.robot_id] = robot;
    }
    for (const core::MemoryEvent& event : m.append_events) {
      fleet.events[event.id] = event;
    }
    fleet.events.erase(fleet.events.begin(),
                       fleet.events.lower_bound(m.erase_events_before));
    if (fleet.empty()) fleets_.erase(it);
    return absl::OkStatus();
  }

  absl::Status SaveIndexSnapshot(
      std::string_view fleet_id,
      const std::function<absl::Status(core::ByteWriter&)>& write,
      const std::function<void()>& written) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    std::vector<char> bytes;
    core::ByteWriter out([&bytes](std::span<const char> chunk) {
      bytes.insert(bytes.end(), chunk.begin(), chunk.end());
    });
    if (absl::Status status = write(out); !status.ok()) return status;
    // The fleet's writes so far: what `write` read (the caller keeps writes
    // out until `written`).
    uint64_t writes = 0;
    {
      absl::MutexLock lock(&mu_);
      writes = writes_[std::string(fleet_id)];
    }
    if (written) written();
    absl::MutexLock lock(&mu_);
    snapshots_[std::string(fleet_id)] = {std::move(bytes), writes};
    return absl::OkStatus();
  }

  absl::Status ReadIndexSnapshot(
      std::string_view fleet_id,
      const engine::IndexSnapshotRead& read) override {
    std::vector<char> bytes;
    {
      absl::MutexLock lock(&mu_);
      auto it = snapshots_.find(fleet_id);
      if (it == snapshots_.end()) {
        return absl::NotFoundError(absl::StrCat("no index snapshot of fleet \"",
                                                std::string(fleet_id), "\""));
      }
      bytes = it->second.bytes;  // a copy: `read` runs outside the lock
    }
    // Kept in memory, never damaged: nothing to check.
    absl::Status status = read({.bytes = bytes, .file = nullptr, .check = [] {
                                  return absl::OkStatus();
                                }});
    // The bytes are the reader's until the read returns (a file's mapping
    // is gone then): a reader that kept a span reads this, not the snapshot.
    std::fill(bytes.begin(), bytes.end(), '\xa5');
    return status;
  }

  bool IndexSnapshotCurrent(std::string_view fleet_id) override {
    absl::MutexLock lock(&mu_);
    auto snapshot = snapshots_.find(fleet_id);
    auto writes = writes_.find(fleet_id);
    return snapshot != snapshots_.end() &&
           snapshot->second.writes ==
               (writes == writes_.end() ? 0 : writes->second);
  }

  absl::StatusOr<std::vector<core::MemoryEvent>> ReadEvents(
      std::string_view fleet_id, uint64_t after_event, size_t limit) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    std::vector<core::MemoryEvent> events;
    absl::MutexLock lock(&mu_);
    auto it = fleets_.find(fleet_id);
    if (it == fleets_.end()) return events;
    const auto& stored = it->second.events;
    for (auto event = stored.upper_bound(after_event);
         event != stored.end() && events.size() < limit; ++event) {
      events.push_back(event->second);
    }
    return events;
  }

  absl::Status DeleteFleet(std::string_view fleet_id,
                           const engine::FleetMeta& kept) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    {
      absl::MutexLock lock(&mu_);
      fleets_.erase(std::string(fleet_id));
      snapshots_.erase(std::string(fleet_id));
      ++writes_[std::string(fleet_id)];
    }
    engine::FleetMutation meta;
    meta.put_meta = true;
    meta.meta = kept;
    return Apply(fleet_id, meta);
  }

  absl::StatusOr<std::vector<engine::FleetAlias>> LoadAliases() override {
    absl::MutexLock lock(&mu_);
    std::vector<engine::FleetAlias> aliases;
    for (const auto& [alias, fleet_id] : aliases_) {
      aliases.push_back({alias, fleet_id});
    }
    return aliases;
  }

  absl::Status PutAlias(std::string_view alias,
                        std::string_view fleet_id) override {
    absl::MutexLock lock(&mu_);
    if (fleet_id.empty()) {
      aliases_.erase(std::string(alias));
    } else {
      aliases_[std::string(alias)] = std::string(fleet_id);
    }
    return absl::OkStatus();
  }

 private:
  absl::Mutex mu_;
  std::map<std::string, std::string> aliases_ ABSL_GUARDED_BY(mu_);
  std::map<std::string, Fleet, std::less<>> fleets_ ABSL_GUARDED_BY(mu_);
  // Index snapshots by fleet id, with the fleet's writes when saved.
  struct Snapshot {
    std::vector<char> bytes;
    uint64_t writes = 0;
  };
  std::map<std::string, Snapshot, std::less<>> snapshots_ ABSL_GUARDED_BY(mu_);
  // Writes of each fleet (Apply, DeleteFleet) since the store was made.
  std::map<std::string, uint64_t, std::less<>> writes_ ABSL_GUARDED_BY(mu_);
};

}  // namespace

std::unique_ptr<engine::MemoryStore> NewInMemoryStore() {
  return std::make_unique<InMemoryStore>();
}

}  // namespace fleetmem::storage
