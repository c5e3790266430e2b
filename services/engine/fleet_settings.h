// A fleet's own settings: made by CreateFleet, changed by UpdateFleet,
// stored durably with the fleet's meta (memory_store.h) and carried by the
// log records that make and change them (fleet_log.h). A fleet made by its
// first upload has none stored and follows the server's configuration
// (EngineOptions::memory, fleet_memory) until an UpdateFleet stores its own.
// Header-only (the ports target).
#ifndef FLEETMEM_SERVICES_ENGINE_FLEET_SETTINGS_H_
#define FLEETMEM_SERVICES_ENGINE_FLEET_SETTINGS_H_

#include <cstdint>
#include <optional>
#include <string>

#include "services/core/memory_options.h"

namespace fleetmem::engine {

// The place index a fleet's codes are searched with. Fixed at creation.
struct IndexSettings {
  enum class Kind {
    kServer,  // the server's configuration (its `index`)
    kExact,   // exact search: every code compared (small fleets)
    kHnsw,    // the HNSW graph from the first code
    kAuto,    // exact below the server's hnsw_from codes, then HNSW
  };
  Kind kind = Kind::kServer;
  // HNSW's graph degree M and search breadth ef (kHnsw, kAuto); 0: the
  // server's.
  int hnsw_m = 0;
  int hnsw_ef_search = 0;
  // The codes the HNSW graph walks on (index::HnswIndexOptions::codes).
  enum class Codes { kServer, kInt8, kFloat };
  Codes hnsw_codes = Codes::kServer;
};

struct FleetSettings {
  // The unit of the fleet's places ("m", "route index"): what its robots
  // agree on; the server never converts. Fixed at creation.
  std::string place_unit;
  // The static memory's parameters. UpdateFleet changes K
  // (clusters_per_batch), N_max (max_traces_per_cluster), K_max
  // (max_clusters), gamma (replay_decay), the forgetting rule
  // (merge_on_forget) and the refresh draw (refresh_pair_radius,
  // refresh_uniform); the rest
  // stay as created (the server's then).
  core::MemoryOptions memory;
  // Retention: traces observed longer ago than this are deleted (0: kept
  // however old).
  int64_t max_age_seconds = 0;
  // Retention: a robot's oldest traces beyond this many are deleted (0: no
  // bound).
  uint64_t max_traces_per_robot = 0;
  IndexSettings index;
};

// What an UpdateFleet changes: the fields set; the others stay.
struct FleetSettingsUpdate {
  std::optional<int> clusters_per_batch;
  std::optional<int> max_traces_per_cluster;
  std::optional<int> max_clusters;
  std::optional<double> replay_decay;
  std::optional<bool> merge_on_forget;
  std::optional<double> refresh_pair_radius;
  std::optional<bool> refresh_uniform;
  std::optional<int64_t> max_age_seconds;
  std::optional<uint64_t> max_traces_per_robot;

  // `settings` with this update applied.
  FleetSettings AppliedTo(FleetSettings settings) const {
    core::MemoryOptions& memory = settings.memory;
    if (clusters_per_batch) memory.clusters_per_batch = *clusters_per_batch;
    if (max_traces_per_cluster) {
      memory.max_traces_per_cluster = *max_traces_per_cluster;
    }
    if (max_clusters) memory.max_clusters = *max_clusters;
    if (replay_decay) memory.replay_decay = *replay_decay;
    if (merge_on_forget) memory.merge_on_forget = *merge_on_forget;
    if (refresh_pair_radius) {
      memory.refresh_pair_radius = *refresh_pair_radius;
    }
    if (refresh_uniform) memory.refresh_uniform = *refresh_uniform;
    if (max_age_seconds) settings.max_age_seconds = *max_age_seconds;
    if (max_traces_per_robot) {
      settings.max_traces_per_robot = *max_traces_per_robot;
    }
    return settings;
  }
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_FLEET_SETTINGS_H_
