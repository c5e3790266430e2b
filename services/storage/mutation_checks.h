// Input checks shared by both stores, so that they accept and refuse the same
// mutations. Internal to services/storage.
#ifndef FLEETMEM_SERVICES_STORAGE_MUTATION_CHECKS_H_
#define FLEETMEM_SERVICES_STORAGE_MUTATION_CHECKS_H_

#include <cstdint>
#include <set>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "services/core/types.h"
#include "services/engine/memory_store.h"

namespace fleetmem::storage::internal {

// A fleet id must be non-empty and free of 0x00 (the key separator).
inline absl::Status CheckFleetId(std::string_view fleet_id) {
  if (fleet_id.empty()) {
    return absl::InvalidArgumentError("fleet_id is empty");
  }
  if (fleet_id.find('\0') != std::string_view::npos) {
    return absl::InvalidArgumentError("fleet_id contains a NUL byte");
  }
  return absl::OkStatus();
}

inline absl::Status CheckRobotId(const std::string& what,
                                 std::string_view robot_id) {
  if (robot_id.find('\0') != std::string_view::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, ".robot_id contains a NUL byte"));
  }
  return absl::OkStatus();
}

// The refusal of a put cluster's trace that comes without its code when the
// store holds none for it (engine::FleetMutation::put_clusters): both stores
// say it alike.
inline absl::Status NoStoredCode(const core::MemoryTrace& trace,
                                 uint64_t cluster_id) {
  return absl::InvalidArgumentError(absl::StrCat(
      "trace ", trace.robot_id, "/", trace.seq, " of cluster ", cluster_id,
      " comes without a code and none is stored for it"));
}

// INVALID_ARGUMENT if a pending trace has no code, a robot id holds 0x00, a put
// cluster or an appended event has id 0, two put clusters share an id, or a
// trace key occurs twice among the put clusters' traces.
inline absl::Status CheckMutation(const engine::FleetMutation& m) {
  absl::Status status;
  auto check_traces = [&](const std::string& what, const auto& traces) {
    for (size_t i = 0; i < traces.size() && status.ok(); ++i) {
      status =
          CheckRobotId(absl::StrCat(what, "[", i, "]"), traces[i].robot_id);
    }
  };
  // A pending trace is stored with its code. (A put cluster's trace may
  // leave its code to the store, which checks that it holds one; an
  // update's code is not read: engine::FleetMutation.)
  for (size_t i = 0; i < m.put_pending.size() && status.ok(); ++i) {
    if (m.put_pending[i].code.empty()) {
      status = absl::InvalidArgumentError(
          absl::StrCat("put_pending[", i, "] has no code"));
    }
  }
  check_traces("put_pending", m.put_pending);
  check_traces("erase_pending", m.erase_pending);
  check_traces("update_traces", m.update_traces);
  check_traces("erase_traces", m.erase_traces);
  check_traces("put_robots", m.put_robots);
  if (!status.ok()) return status;
  std::set<uint64_t> cluster_ids;
  std::set<core::TraceKey> clustered;
  for (size_t i = 0; i < m.put_clusters.size(); ++i) {
    const core::Cluster& cluster = m.put_clusters[i];
    if (cluster.id == 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("put_clusters[", i, "].id is 0"));
    }
    if (!cluster_ids.insert(cluster.id).second) {
      return absl::InvalidArgumentError(
          absl::StrCat("cluster ", cluster.id, " is put twice"));
    }
    check_traces(absl::StrCat("put_clusters[", i, "].traces"), cluster.traces);
    if (!status.ok()) return status;
    for (const core::MemoryTrace& trace : cluster.traces) {
      if (!clustered.insert(trace.key()).second) {
        return absl::InvalidArgumentError(
            absl::StrCat("trace ", trace.robot_id, "/", trace.seq,
                         " is put twice among put_clusters"));
      }
    }
  }
  for (size_t i = 0; i < m.append_events.size(); ++i) {
    if (m.append_events[i].id == 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("append_events[", i, "].id is 0"));
    }
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::storage::internal

#endif  // FLEETMEM_SERVICES_STORAGE_MUTATION_CHECKS_H_
