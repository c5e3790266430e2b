// Domain types of the fleet memory: memory traces, clusters and events.
// Plain data; no I/O, no proto.
#ifndef FLEETMEM_SERVICES_CORE_TYPES_H_
#define FLEETMEM_SERVICES_CORE_TYPES_H_

#include <compare>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

namespace fleetmem::core {

// Place p_k of an observation in the fleet's map frame (metres, radians).
struct Place {
  double x = 0.0;
  double y = 0.0;
  double z = 0.0;
  double yaw = 0.0;
};

// Identity of a trace within a fleet: (robot, per-robot sequence number).
struct TraceKey {
  std::string robot_id;
  uint64_t seq = 0;

  friend auto operator<=>(const TraceKey&, const TraceKey&) = default;
  friend bool operator==(const TraceKey&, const TraceKey&) = default;
  template <typename H>
  friend H AbslHashValue(H h, const TraceKey& key) {
    return H::combine(std::move(h), key.robot_id, key.seq);
  }
};

// Memory trace m_k = (z_k, p_k, R_k) (BioSLAM Sec. V) with provenance.
struct MemoryTrace {
  std::string robot_id;
  uint64_t seq = 0;
  std::string domain;
  std::vector<float> code;  // z_k, as uploaded (not normalised)
  Place place;              // p_k
  float reward = 0.0f;      // R_k = R_ex + R_in (Eq. 13)
  float reward_external = 0.0f;
  float reward_internal = 0.0f;
  int64_t timestamp_ns = 0;
  uint32_t replay_count = 0;  // n_k (Eq. 18)
  std::string encoder_version;
  uint64_t cluster_id = 0;  // 0 while pending
  // Opaque keyframe data for peers (a laser scan for SLAM), <= 16 KiB.
  std::string attachment;

  TraceKey key() const { return TraceKey{robot_id, seq}; }
};

// New rewards of one held trace (a fleet's UpdateRewards): R_ex and R_in;
// R = R_ex + R_in (Eq. 13).
struct RewardUpdate {
  TraceKey key;
  float reward_external = 0.0f;
  float reward_internal = 0.0f;
};

// One cluster S_i of the static memory with its centroid mu_i in
// feature-spatial space (Eq. 14). Ids are never reused and grow with age, so a
// smaller id is an older cluster (forgetting breaks ties towards it).
struct Cluster {
  uint64_t id = 0;
  std::string robot_id;  // robot whose segment produced the cluster
  std::vector<float> centroid;
  std::vector<MemoryTrace> traces;

  double MeanReward() const;
};

// kClusterMerged: forgetting merged the cluster into `merged_into`
// (MemoryOptions::merge_on_forget); its id is no longer held.
// kTracesDeleted: a DeleteTraces removed `traces_dropped` traces of the
// cluster (0: of the pending traces); `trace_count` is what the cluster
// holds after it (0: it left, empty).
enum class EventType {
  kClusterAdded = 1,
  kClusterForgotten = 2,
  kClusterMerged = 3,
  kTracesDeleted = 4,
};

// A change of a fleet's static memory that robots and dashboards can watch.
struct MemoryEvent {
  uint64_t id = 0;  // strictly increasing within a fleet, from 1
  EventType type = EventType::kClusterAdded;
  uint64_t cluster_id = 0;
  uint32_t trace_count = 0;
  std::string robot_id;
  std::string domain;  // most frequent domain of the cluster's traces
  Place centroid_place;
  float mean_reward = 0.0f;
  int64_t timestamp_ns = 0;
  // kClusterMerged: the cluster that took this one's traces, and how many
  // traces of the two the merge dropped (trace_count is this cluster's
  // before the merge; the memory holds traces_dropped fewer traces after).
  // kTracesDeleted: the traces deleted (trace_count: those left).
  uint64_t merged_into = 0;
  uint32_t traces_dropped = 0;
};

// Summary event for `cluster` (id and timestamp left for the caller).
MemoryEvent DescribeCluster(const Cluster& cluster, EventType type);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_TYPES_H_
