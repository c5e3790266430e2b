#include "services/core/memory_options.h"

#include <cmath>

#include "absl/strings/str_cat.h"

namespace fleetmem::core {
namespace {

absl::Status OutOfRange(const char* field, double value, const char* rule) {
  return absl::InvalidArgumentError(
      absl::StrCat("MemoryOptions.", field, " is ", value, "; must be ", rule));
}

}  // namespace

absl::Status ValidateMemoryOptions(const MemoryOptions& options) {
  if (options.clusters_per_batch < 1) {
    return OutOfRange("clusters_per_batch", options.clusters_per_batch, ">= 1");
  }
  if (options.max_traces_per_cluster < 1) {
    return OutOfRange("max_traces_per_cluster", options.max_traces_per_cluster,
                      ">= 1");
  }
  if (options.max_clusters < 1) {
    return OutOfRange("max_clusters", options.max_clusters, ">= 1");
  }
  // Written so that NaN fails every check.
  if (!(options.replay_decay >= 0.0 && options.replay_decay <= 1.0)) {
    return OutOfRange("replay_decay", options.replay_decay, "in [0, 1]");
  }
  if (!(options.reward_floor > 0.0) || std::isinf(options.reward_floor)) {
    return OutOfRange("reward_floor", options.reward_floor,
                      "positive and finite");
  }
  if (!(options.spatial_scale_m > 0.0) || std::isinf(options.spatial_scale_m)) {
    return OutOfRange("spatial_scale_m", options.spatial_scale_m,
                      "positive and finite");
  }
  if (options.kmeans_max_iterations < 1) {
    return OutOfRange("kmeans_max_iterations", options.kmeans_max_iterations,
                      ">= 1");
  }
  if (options.forgetting_exact_below < 2) {
    return OutOfRange("forgetting_exact_below", options.forgetting_exact_below,
                      ">= 2");
  }
  if (!(options.refresh_pair_radius >= 0.0) ||
      std::isinf(options.refresh_pair_radius)) {
    return OutOfRange("refresh_pair_radius", options.refresh_pair_radius,
                      ">= 0 and finite");
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::core
