// One robot's part of an encoder migration (docs/api.md, "Aliases and
// encoder migration", step 3; fleetmem-robot --migrate-from): the robot
// re-encodes what the old fleet still holds of its own traces with its new
// encoder, from its own observations, and uploads them to the new fleet
// under the same (robot, seq):
//
//   1. what is still queued for the old fleet is uploaded there first (an
//      acknowledged observation is never dropped; it is migrated below);
//   2. the open segment (codes of the old encoder, not sealed) is
//      discarded: its observations are made again with the new encoder;
//   3. by seq, in batches: GetTraces from the old fleet (forgotten or
//      deleted traces are not brought back), each found trace's
//      observation read again from the source (its index kept by the
//      robot's store), encoded with the new encoder, R_in recomputed under
//      it (Eq. 12, the same seeded perturbation), R_ex, place, domain, time
//      and attachment kept; uploaded to the new fleet; the batch's last seq
//      written down, so that a migration killed at any point resumes there
//      (a repeated batch is answered as duplicates);
//   4. the data dir moves to the new fleet (its watch cursor restarts).
//
// Traces sealed before the robot's store kept source indices cannot be
// re-encoded: they are counted and stay in the old fleet only.
#ifndef FLEETMEM_CLIENTS_ROBOT_RUNTIME_MIGRATION_H_
#define FLEETMEM_CLIENTS_ROBOT_RUNTIME_MIGRATION_H_

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "clients/cpp/fleetmem_client.h"
#include "clients/robot/memory/robot_store.h"
#include "clients/robot/sensing/encoder.h"
#include "clients/robot/sensing/observation_source.h"

namespace fleetmem::robot {

struct MigrationOptions {
  // The fleet (or alias) the robot's traces are in, and the fleet made for
  // the new encoder.
  std::string from_fleet;
  std::string to_fleet;
  // The robot's --seed: R_in's perturbations (agent.h's InternalRewardOf).
  uint64_t seed = 1;
  // Traces per GetTraces and per upload.
  size_t batch = 500;
  // How long the queue's last upload to the old fleet may take to be
  // applied there (what GetTraces then reads).
  std::chrono::milliseconds apply_wait{60000};
  // Progress lines (default: none).
  std::function<void(std::string_view)> log;
};

// What the migration did, this run and before it (a resumed one).
struct MigrationSummary {
  // Queued traces uploaded to the old fleet before the migration.
  uint64_t queued_sent = 0;
  // Open observations discarded (made again with the new encoder).
  uint64_t open_discarded = 0;
  // Re-encoded and acknowledged by the new fleet, in all (a resumed
  // migration's earlier runs included).
  uint64_t migrated = 0;
  // This run's: acknowledged as held already (a batch repeated after a
  // kill), and the robot's traces the old fleet no longer holds
  // (forgotten, deleted): not brought back.
  uint64_t duplicates = 0;
  uint64_t not_held = 0;
  // Sealed before the store kept source indices: not re-encodable.
  uint64_t no_source = 0;
  // The data dir had moved to the new fleet already: nothing was done.
  bool already_done = false;
};

// Runs the migration on `store` (a data dir of `from_fleet`, or of
// `to_fleet` once migrated: then already_done). `client` retries what a
// retry can mend; any other error stops the migration with what is done
// written down (a rerun resumes). FAILED_PRECONDITION if the data dir
// belongs to neither fleet.
absl::StatusOr<MigrationSummary> MigrateRobot(const MigrationOptions& options,
                                              client::Client& client,
                                              const ObservationSource& source,
                                              const Encoder& encoder,
                                              RobotStore& store);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_RUNTIME_MIGRATION_H_
