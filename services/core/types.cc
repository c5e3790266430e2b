#include "services/core/types.h"

#include <cmath>
#include <map>
#include <string>

namespace fleetmem::core {

double Cluster::MeanReward() const {
  if (traces.empty()) return 0.0;
  double sum = 0.0;
  for (const MemoryTrace& trace : traces) sum += trace.reward;
  return sum / static_cast<double>(traces.size());
}

MemoryEvent DescribeCluster(const Cluster& cluster, EventType type) {
  MemoryEvent event;
  event.type = type;
  event.cluster_id = cluster.id;
  event.trace_count = static_cast<uint32_t>(cluster.traces.size());
  event.robot_id = cluster.robot_id;
  event.mean_reward = static_cast<float>(cluster.MeanReward());
  if (cluster.traces.empty()) return event;

  // Most frequent domain; std::map iterates in lexicographic order, so the
  // first maximum found is the smallest tied domain.
  std::map<std::string, size_t> domain_counts;
  for (const MemoryTrace& trace : cluster.traces) ++domain_counts[trace.domain];
  size_t best = 0;
  for (const auto& [domain, count] : domain_counts) {
    if (count > best) {
      best = count;
      event.domain = domain;
    }
  }

  // Mean place; yaw is an angle, so it is averaged on the circle.
  double x = 0.0, y = 0.0, z = 0.0, sin_yaw = 0.0, cos_yaw = 0.0;
  for (const MemoryTrace& trace : cluster.traces) {
    x += trace.place.x;
    y += trace.place.y;
    z += trace.place.z;
    sin_yaw += std::sin(trace.place.yaw);
    cos_yaw += std::cos(trace.place.yaw);
  }
  const double n = static_cast<double>(cluster.traces.size());
  event.centroid_place.x = x / n;
  event.centroid_place.y = y / n;
  event.centroid_place.z = z / n;
  event.centroid_place.yaw =
      (sin_yaw == 0.0 && cos_yaw == 0.0) ? 0.0 : std::atan2(sin_yaw, cos_yaw);
  return event;
}

}  // namespace fleetmem::core
