// The durable engine::MemoryStore: one RocksDB database holding every fleet.
//
// Semantics shared with NewInMemoryStore (services/storage/in_memory_store.h):
// - Apply(fleet, m) is all-or-nothing. It runs in the order of
//   engine::FleetMutation: erase_pending, erase_clusters (with every trace of
//   the cluster), erase_traces (also dropped from their cluster's member
//   list), put_meta, put_pending, put_clusters, update_traces, put_robots,
//   append_events. Erasing something absent is not an error.
// - put_clusters replaces a cluster whole: its traces are stored with
//   cluster_id = the cluster's id and in the given order; traces of an earlier
//   version of the cluster that are no longer listed are erased; a trace that
//   belonged to another cluster moves (a trace is in exactly one cluster).
//   A trace put without a code keeps the code stored for it before the
//   mutation (its erasures do not take it); INVALID_ARGUMENT, nothing
//   applied, when none is (a new or a pending trace).
// - update_traces rewrites a static-memory trace and keeps its cluster and
//   its stored code (the code given is not read); an update of a trace
//   that is not in the static memory (e.g. forgotten in between) is
//   ignored.
// - A cluster both erased and put in one mutation ends up stored (erasures
//   come first).
// - INVALID_ARGUMENT, with nothing applied: empty fleet id, 0x00 in a fleet or
//   robot id, cluster or event id 0, a cluster or trace put twice in one
//   mutation, a pending trace without a code.
// - LoadFleet returns meta (defaults if never put), pending traces by
//   (robot_id, seq), clusters by id with their traces, robots by id. A fleet
//   appears in ListFleets while it has any stored record.
#ifndef FLEETMEM_SERVICES_STORAGE_ROCKSDB_STORE_H_
#define FLEETMEM_SERVICES_STORAGE_ROCKSDB_STORE_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "services/engine/fleet_log.h"
#include "services/engine/memory_store.h"

namespace fleetmem::storage {

struct RocksDbStoreOptions {
  // Directory of the database. Required.
  std::string path;
  // Sync the write-ahead log before Apply returns OK, so that an
  // acknowledged change survives a machine crash. Off, it still survives a
  // process crash.
  bool sync = true;
  // Create the directory (and its missing parents) and an empty database if
  // there is none at `path`; off, a missing database is an error.
  bool create_if_missing = true;
  // Shared LRU block cache for reads; 0 disables the block cache.
  size_t block_cache_bytes = size_t{64} << 20;
  // Size of one memtable before it is flushed to a table file.
  size_t write_buffer_bytes = size_t{32} << 20;
  // Bloom filter bits per key in table files (speeds up point reads of
  // absent keys); 0 disables the filter.
  int bloom_bits_per_key = 10;
  // Background threads for flushes and compactions.
  int background_jobs = 2;
  // Compress table files: LZ4 (else Snappy) for upper levels and ZSTD for the
  // last level, whichever this RocksDB build supports.
  bool compress = true;
  // Disk reserve: Apply refuses a write (RESOURCE_EXHAUSTED, nothing
  // written) when the filesystem of `path` would have less than this many
  // bytes free after it. RocksDB is never driven into ENOSPC by our writes
  // (Debian's RocksDB build asserts on a write-ahead-log error), so
  // flushes and compactions keep the room they need, reads go on, and
  // writes resume by themselves once space is freed. 0 disables the check.
  uint64_t min_free_bytes = uint64_t{64} << 20;
  // Free bytes on the filesystem holding `path` (statvfs by default; tests
  // inject their own).
  std::function<absl::StatusOr<uint64_t>(const std::string& path)> free_bytes;
};

// Opens (or creates) the database at `options.path`. Errors:
// INVALID_ARGUMENT for an empty path or, with create_if_missing off, a
// missing database; UNAVAILABLE if the directory cannot be created or opened
// (permissions, not a directory, locked by another process) or on I/O
// errors; DATA_LOSS if the database is corrupt; FAILED_PRECONDITION if it was
// written with another key layout version. The messages name the path and
// carry RocksDB's own message.
//
// The returned store is thread-safe: reads run in parallel, Apply calls are
// serialised. Destroying it closes the database (writes already returned OK
// are in the write-ahead log; nothing else is flushed). Errors of later calls:
// RESOURCE_EXHAUSTED (below the disk reserve, or disk full: nothing of the
// write is stored), UNAVAILABLE / INTERNAL for other RocksDB failures (after
// a failed write the next Apply first asks RocksDB to resume), DATA_LOSS
// naming the key for a record that does not decode. A failed write never
// ends the process.
absl::StatusOr<std::unique_ptr<engine::MemoryStore>> OpenRocksDbStore(
    const RocksDbStoreOptions& options);

// The engine's two ports over one data directory: the store, and the
// fleets' ingest log (segment_log.h) in PATH/ingest-log beside it.
struct LocalStorage {
  std::unique_ptr<engine::MemoryStore> store;
  // Owned by `store`, valid while it lives: the two keep each other's
  // rules (a trim first syncs the store's write-ahead log, since the
  // applies of log entries are unsynced; an append keeps the store's disk
  // reserve, dropping the log's spare segments when it is short; a
  // Checkpoint copies the log with the store).
  engine::FleetLog* log = nullptr;
};

// OpenRocksDbStore, with the ingest log it opens (OpenRocksDbStore alone:
// a store whose log is still opened, recovered and kept, unused).
absl::StatusOr<LocalStorage> OpenLocalStorage(
    const RocksDbStoreOptions& options);

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_ROCKSDB_STORE_H_
