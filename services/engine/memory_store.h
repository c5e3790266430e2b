// The storage port of the engine: where a fleet's static memory, pending
// traces, received sequence numbers and events live durably: the applied
// state, and nothing else (the uploads acknowledged and not applied yet are
// in the log port, fleet_log.h). Implementations: services/storage
// (RocksDB; in-memory for tests).
#ifndef FLEETMEM_SERVICES_ENGINE_MEMORY_STORE_H_
#define FLEETMEM_SERVICES_ENGINE_MEMORY_STORE_H_

#include <cstdint>
#include <functional>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/core/byte_stream.h"
#include "services/core/seq_set.h"
#include "services/core/types.h"
#include "services/engine/fleet_settings.h"

namespace fleetmem::engine {

// Per-fleet facts that are not traces, clusters or events.
struct FleetMeta {
  uint32_t code_dimension = 0;  // fixed by the first upload
  std::string encoder_version;  // fixed by the first upload
  uint64_t next_cluster_id = 1;
  uint64_t next_event_id = 1;
  uint64_t consolidations = 0;
  uint64_t clusters_forgotten = 0;
  // Oldest event still stored (older ones were dropped by the retention
  // bound); 0 or 1 when none ever was.
  uint64_t first_event_id = 1;
  // Distributed mode: the last entry of the fleet's log whose upload is in
  // this state (0: none, and always in the embedded mode). Entries after it
  // may be applied too (uploads are idempotent); none before it is missing.
  uint64_t log_position = 0;
  // The fleet's own settings (CreateFleet, UpdateFleet); none: the
  // server's configuration.
  std::optional<FleetSettings> settings;
};

// A name that calls accept in place of a fleet id (fleet_aliases.h).
struct FleetAlias {
  std::string alias;
  std::string fleet_id;
};

// Counters kept per robot (stats), persisted with the robot's SeqSet.
struct RobotRecord {
  std::string robot_id;
  core::SeqSet received;  // every seq ever accepted from the robot
  uint64_t replayed = 0;  // traces handed to this robot by SampleReplay
  // The robot's last SampleReplay that carried a request id, and the traces
  // it drew: a retry with the same id gets them again, uncounted.
  std::string last_sample_request_id;
  std::vector<core::TraceKey> last_sample;
};

// Everything stored for one fleet, as loaded at start-up.
struct FleetRecord {
  std::string fleet_id;
  FleetMeta meta;
  std::vector<core::MemoryTrace> pending;  // awaiting consolidation
  std::vector<core::Cluster> clusters;     // with their traces, by id
  std::vector<RobotRecord> robots;
};

// A fleet's whole state: what LoadFleet gives and its events (distributed
// mode's snapshots, MemoryEngine::ExportFleet and RestoreFleet; encoded by
// services/storage/fleet_image.h).
struct FleetImage {
  FleetRecord record;
  std::vector<core::MemoryEvent> events;  // ascending by id
};

// One atomic change of a fleet. Applied in this order: erasures, then puts.
struct FleetMutation {
  bool put_meta = false;
  FleetMeta meta;
  std::vector<core::MemoryTrace> put_pending;
  std::vector<core::TraceKey> erase_pending;
  // Clusters (centroid + membership) and their traces. A put cluster's
  // traces are written with it; an erased cluster's traces are erased.
  // A put trace with an empty code keeps the code the store holds for it:
  // a trace of the static memory as the store held it before this
  // mutation (in this cluster or another, one that this mutation erases
  // included), so that a merge or a changed cluster rewrites no code (a
  // trace's code never changes once stored). The store holds no code for
  // it (a new or a pending trace): INVALID_ARGUMENT, nothing applied.
  std::vector<core::Cluster> put_clusters;
  std::vector<uint64_t> erase_clusters;
  // Traces of the static memory whose fields changed (e.g. replay_count);
  // their cluster already exists. A trace the store does not hold is
  // skipped. An update never changes a trace's code: the store keeps the
  // code it holds and writes the other fields only (the code given, which
  // may be empty, is not read).
  std::vector<core::MemoryTrace> update_traces;
  // The engine vouches that every update_traces entry is held, with the
  // cluster_id it carries (a replay draw, under the fleet's writer lock):
  // the store may write them without reading them first.
  bool update_traces_held = false;
  // Traces removed from an existing cluster (downsampling never does this
  // today, but forgetting of single traces may).
  std::vector<core::TraceKey> erase_traces;
  std::vector<RobotRecord> put_robots;
  std::vector<core::MemoryEvent> append_events;
  // Events with id < this are erased (event retention); 0 erases none.
  uint64_t erase_events_before = 0;
  // False: the write need not be synced before Apply returns (it is still
  // in the write-ahead log, so a process crash keeps it; a machine crash
  // may lose it with everything written after it). For the apply of a log
  // entry: the log is the durable copy, and applying it again after such
  // a loss changes nothing.
  bool sync = true;

  // True if applying the mutation would change nothing. Inline: the ports
  // target is header-only.
  bool empty() const {
    return !put_meta && put_pending.empty() && erase_pending.empty() &&
           put_clusters.empty() && erase_clusters.empty() &&
           update_traces.empty() && erase_traces.empty() &&
           put_robots.empty() && append_events.empty() &&
           erase_events_before == 0;
  }
};

// What a store hands to a read of an index snapshot
// (MemoryStore::ReadIndexSnapshot).
struct IndexSnapshotBytes {
  // The snapshot as it was saved, handed before its checksum is checked so
  // that a reader can parse them while `check` runs: a reader acts on
  // nothing it read from them before `check` returned OK.
  std::span<const char> bytes;
  // Where they lie in a file the store never changes (the RocksDB store's
  // mapped file); nullptr for a store that keeps them in memory. A reader
  // may keep the file open and read parts of it later.
  const core::FileBytes* file = nullptr;
  // Checks `bytes` against the checksum they were saved with, once (a
  // second call returns the first verdict): OK, or DATA_LOSS, and the
  // store discards the snapshot. On the caller's thread (0.11 s at
  // 1,000,000 traces with the file in the page cache, 8 s at 10,000,000
  // on a 24 GiB host). Thread-safe; valid until the read returns.
  std::function<absl::Status()> check;
};

// Reads an index snapshot (MemoryStore::ReadIndexSnapshot).
using IndexSnapshotRead =
    std::function<absl::Status(const IndexSnapshotBytes&)>;

// Thread-safe. Every method returns a non-OK status on storage failure,
// never throws.
class MemoryStore {
 public:
  virtual ~MemoryStore() = default;

  // Ids of every fleet with stored state, sorted.
  virtual absl::StatusOr<std::vector<std::string>> ListFleets() = 0;

  // Everything stored for `fleet_id` (empty record if nothing is).
  virtual absl::StatusOr<FleetRecord> LoadFleet(std::string_view fleet_id) = 0;

  // LoadFleet, with the code of each trace of a cluster for which
  // `code_held_elsewhere(key)` is true left empty (pending traces keep
  // theirs): a restart whose index snapshot holds those codes does not
  // read them a second time (1 GB at 1,000,000 256-d traces). The function
  // is asked once per such trace, on the calling thread, after the fleet's
  // other records are read (so it may wait for what it needs); a null
  // function keeps every code. Pure virtual, so that a decorator cannot
  // fall back to reading every code without saying so (the metrics'
  // decorator did until 2026-11-30).
  virtual absl::StatusOr<FleetRecord> LoadFleetWithoutHeldCodes(
      std::string_view fleet_id,
      const std::function<bool(const core::TraceKey&)>&
          code_held_elsewhere) = 0;

  // LoadFleet without the clusters and their traces (meta, pending traces,
  // robots): for a load that takes the clusters from the fleet's index
  // snapshot (IndexSnapshotCurrent). Pure virtual, as above.
  virtual absl::StatusOr<FleetRecord> LoadFleetWithoutClusters(
      std::string_view fleet_id) = 0;

  // Applies `mutation` atomically; when OK is returned the change is durable
  // (survives a process crash, and with sync on, a machine crash).
  virtual absl::Status Apply(std::string_view fleet_id,
                             const FleetMutation& mutation) = 0;

  // Up to `limit` events of the fleet with id > after_event, ascending.
  virtual absl::StatusOr<std::vector<core::MemoryEvent>> ReadEvents(
      std::string_view fleet_id, uint64_t after_event, size_t limit) = 0;

  // Writes a consistent copy of everything stored into the new directory
  // `directory` (it must not exist; its parent must): a store opened there
  // holds the state of one instant, with every Apply that returned before
  // the call. Writes go on meanwhile. UNIMPLEMENTED for a store that keeps
  // nothing on disk; on any error nothing is left at `directory`.
  virtual absl::Status Checkpoint(const std::string& directory) {
    return absl::UnimplementedError(
        "this store keeps nothing on disk and cannot take snapshots");
  }

  // Index snapshots (MemoryEngine::SaveIndexSnapshots): bytes that let a
  // load of a fleet skip rebuilding its place index. A snapshot describes
  // the fleet as it was when written; the engine reconciles it with the
  // stored state at load (traces added or removed since), so a snapshot
  // stays usable after later writes and after a crash. Stores that keep
  // nothing on disk may hold them in memory.
  //
  // Stores what `write` writes as the fleet's snapshot, replacing the
  // earlier one once it is complete (durably, for a store on disk). If
  // `write` or the store fails, the earlier snapshot, if any, is kept and
  // the error is returned. `written`, if set, is called once `write` has
  // returned OK and the store holds every byte it wrote, before they are
  // made durable (fsync, rename): from then on the caller may change what
  // `write` read. Calls for one fleet must not overlap. UNIMPLEMENTED by
  // default.
  virtual absl::Status SaveIndexSnapshot(
      std::string_view fleet_id,
      const std::function<absl::Status(core::ByteWriter&)>& write,
      const std::function<void()>& written = nullptr) {
    return absl::UnimplementedError("this store keeps no index snapshots");
  }
  // Calls `read` with the fleet's latest snapshot (IndexSnapshotBytes) and
  // returns its status; the snapshot is kept. NOT_FOUND when there is none
  // (`read` is not called); DATA_LOSS when it is damaged (its frame, before
  // `read`; or its checksum, the verdict of `check`): it is then discarded.
  // A `read` that returns OK without calling `check` gets its verdict.
  virtual absl::Status ReadIndexSnapshot(std::string_view fleet_id,
                                         const IndexSnapshotRead& read) {
    return absl::NotFoundError("this store keeps no index snapshots");
  }
  // True if the fleet's snapshot (the one ReadIndexSnapshot reads now) was
  // saved after the store's last write of the fleet, so that it describes
  // exactly what the store holds: the engine may then take the fleet's
  // clusters from it rather than read them (a restart after a clean stop).
  // A write of the fleet (Apply, DeleteFleet) makes it false until the
  // next SaveIndexSnapshot; so does anything the store cannot vouch for
  // (the RocksDB store: a start after a crash, or after a build that keeps
  // no such record wrote the store). A SaveIndexSnapshot of the fleet that
  // ends meanwhile may change which snapshot that is: callers keep saves
  // out. False by default.
  virtual bool IndexSnapshotCurrent(std::string_view fleet_id) { return false; }

  // Removes everything stored for the fleet (its state, events and index
  // snapshot) and stores `kept` as its meta instead, in one atomic write
  // (DeleteFleet: `kept` holds the log position of the delete and where
  // event ids go on, and no shape, so the fleet does not exist). Then
  // frees the disk the fleet took where the store can (a failure to is
  // logged, not returned: the delete is done). UNIMPLEMENTED by default.
  virtual absl::Status DeleteFleet(std::string_view fleet_id,
                                   const FleetMeta& kept) {
    return absl::UnimplementedError("this store cannot delete fleets");
  }

  // Fleet aliases (fleet_aliases.h), beside the fleets: every alias and
  // its fleet, sorted by alias.
  virtual absl::StatusOr<std::vector<FleetAlias>> LoadAliases() {
    return absl::UnimplementedError("this store keeps no aliases");
  }
  // Sets `alias` to name `fleet_id` (empty: erases it), durably.
  virtual absl::Status PutAlias(std::string_view alias,
                                std::string_view fleet_id) {
    return absl::UnimplementedError("this store keeps no aliases");
  }

  // Approximate bytes the store takes on disk (0 when it keeps nothing
  // there), for metrics.
  virtual uint64_t ApproximateDiskBytes() { return 0; }

  // The store's own memory outside the traces it serves, by kind (e.g.
  // RocksDB's "memtables", "table_readers", "block_cache"), for metrics;
  // empty where the store reports none.
  virtual std::vector<std::pair<std::string, uint64_t>> MemoryUsage() {
    return {};
  }
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_MEMORY_STORE_H_
