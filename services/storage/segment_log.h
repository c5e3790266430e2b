// The ingest log beside the RocksDB store (the engine's FleetLog port,
// engine/fleet_log.h; opened with the store, OpenLocalStorage): per fleet,
// append-only segment files of checksummed records, each append one write and
// one fdatasync, applied segments deleted or kept for reuse.
//
// Why not in RocksDB, where it was until 2026-11: an entry lives from its
// acknowledgement until the applier has applied it, and in RocksDB it was
// written to the write-ahead log (software CRC in Debian's build), copied
// into a memtable, flushed to a table file and compacted (zstd at the
// bottom level) before its deletion reached it. During a burst of one
// upload stream compaction took 0.68 of this machine's two cores
// (bench/write_path_profile.sh); here an entry is written once, checksummed
// with XXH3, and read back once by the applier. An append of 200 traces
// takes 0.62x the time of the synced RocksDB batch it replaced
// (bench/ingest_log_bench.cc).
//
// Layout: DIRECTORY/f-<fleet id>/<first sequence, 20 digits>.seg, and
// spare-<n>.seg: trimmed segments kept for reuse, because fdatasync of a
// write that does not grow a file need not journal its size.
// Record: magic "FMLG" | XXH3-64 of the rest (uint64) | segment (its first
//   sequence, uint64) | sequence (uint64) | payload bytes (uint32) |
//   payload (record_codec's logged record: an upload or a call)
// all little-endian. Each append's records end with a padding record
// (sequence 0; to the next 4 KiB with O_DIRECT). Where a segment holds bytes
// that are not the next whole, intact record of this segment, the reader looks
// for the next intact record of this segment after them: none means a torn tail
// (the write in flight at a crash, never acknowledged) or what a reused file
// held before, and the segment ends there; one means a damaged middle
// (a flipped bit, a bad sector): the entries between are lost, reported
// (Losses, an error in the log), and the records after the damage are
// read as usual. A write that failed is undone by zeroing what it wrote,
// so that no record of it is found later.
#ifndef FLEETMEM_SERVICES_STORAGE_SEGMENT_LOG_H_
#define FLEETMEM_SERVICES_STORAGE_SEGMENT_LOG_H_

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "services/engine/fleet_log.h"

namespace fleetmem::storage {

struct SegmentLogOptions {
  // Where the fleets' segments live; created if missing.
  std::string directory;
  // A segment takes no more appends once it holds this many bytes (an
  // append may take it past; 16 MiB: about 15,000 traces of 256-d).
  uint64_t segment_bytes = uint64_t{16} << 20;
  // Trimmed segments a fleet keeps for reuse; more are deleted. A fleet
  // whose log is applied keeps its last segment and these on disk (up to
  // 32 MiB by default).
  size_t spare_segments = 1;
  // Asked before each append with the bytes it writes: a non-OK status
  // (e.g. RESOURCE_EXHAUSTED, a disk reserve) refuses the append. May be
  // empty.
  std::function<absl::Status(std::string_view fleet_id, uint64_t bytes)>
      check_room;
  // Called before segments are removed by Trim: it must make durable what
  // the trimmed entries were applied to (the store's unsynced writes). May
  // be empty.
  std::function<absl::Status()> before_trim;
};

// Thread-safe. Appends of one fleet must not overlap (the write path's
// leader makes them one at a time); reads and trims may run beside them.
class SegmentLog final : public engine::FleetLog {
 public:
  // Opens the log at options.directory, reading every fleet's segments
  // (checksums included). Damaged entries are passed over and reported
  // (Losses), never an error of Open.
  static absl::StatusOr<std::unique_ptr<SegmentLog>> Open(
      SegmentLogOptions options);
  ~SegmentLog() override;
  SegmentLog(const SegmentLog&) = delete;
  SegmentLog& operator=(const SegmentLog&) = delete;

  // Appends `entries` under the sequences after the fleet's last (and
  // after options.above) as one write and fdatasync. On error nothing of
  // them is read back, now or after a restart, unless the status says it
  // could not be undone. Ids are not kept.
  absl::StatusOr<std::vector<engine::AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const engine::LogAppend> entries,
      const engine::AppendOptions& options) override;
  // Up to `max_entries` entries with sequence > `after`, ascending.
  absl::StatusOr<std::vector<engine::LogEntry>> Read(
      std::string_view fleet_id, uint64_t after, size_t max_entries) override;
  // The fleet's entries found damaged, at Open or by Read (which passes
  // over them), in the order found.
  std::vector<engine::LostLogEntries> Losses(
      std::string_view fleet_id) override;
  // Removes the segments whose entries all have sequence <= `through`
  // (but not the one appends go to, so that the fleet's last sequence is
  // known after a restart). Entries at or below `through` in the rest stay
  // readable; callers read past them.
  absl::Status Trim(std::string_view fleet_id, uint64_t through) override;
  // The first entry still held (Trim keeps some) and the last given.
  absl::StatusOr<engine::LogBounds> Bounds(std::string_view fleet_id) override;
  // The fleets whose log ever held an entry, sorted.
  absl::StatusOr<std::vector<std::string>> Fleets() override;
  // Bytes of records in every fleet's segments (not counting the spares
  // kept for reuse, at most spare_segments * segment_bytes a fleet).
  uint64_t Bytes();
  // Bytes of the spares kept for reuse.
  uint64_t SpareBytes();
  // Deletes every fleet's spares (the disk is short: a spare only pays
  // where space is plenty); returns the bytes freed.
  uint64_t DropSpares();

  // Calls `first` (may be empty), then copies every fleet's segments, as far
  // as they hold records, into a new log at `directory`, synced; no Trim
  // runs meanwhile. For a checkpoint: `first` copies the store, and the log
  // copied after it holds every entry the store's copy has not applied
  // (and perhaps later ones, applied again idempotently).
  absl::Status CopyTo(const std::string& directory,
                      const std::function<absl::Status()>& first);

 private:
  struct Segment;
  struct Fleet;
  explicit SegmentLog(SegmentLogOptions options);
  Fleet* Find(std::string_view fleet_id);
  Fleet& FindOrMake(std::string_view fleet_id);
  // Every fleet, sorted by id (a Fleet is never erased).
  std::vector<Fleet*> AllFleets();
  absl::Status LoadFleet(const std::string& fleet_id, const std::string& path);
  absl::StatusOr<std::shared_ptr<Segment>> StartSegment(Fleet& fleet,
                                                        uint64_t first);
  static absl::Status OpenForAppends(Segment& segment);
  // The segment an append whose first entry is `first_sequence` goes to:
  // the fleet's last, at its end, while it takes more; or a new one
  // (`started`: not yet in the fleet's list). Ready for appends.
  struct Target {
    std::shared_ptr<Segment> segment;
    uint64_t offset = 0;
    bool started = false;
  };
  absl::StatusOr<Target> TargetOf(Fleet& fleet, std::string_view fleet_id,
                                  uint64_t first_sequence);
  // The sequence an append's first entry gets: after the fleet's last and
  // after options.above; FAILED_PRECONDITION for options.only_first on a
  // log that held an entry.
  absl::StatusOr<uint64_t> NextSequence(Fleet& fleet,
                                        const engine::AppendOptions& options);

  const SegmentLogOptions options_;
  absl::Mutex trim_mu_;  // held by Trim and CopyTo
  absl::Mutex mu_;       // guards fleets_ (the map; a Fleet is never erased)
  std::map<std::string, std::unique_ptr<Fleet>, std::less<>> fleets_;
};

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_SEGMENT_LOG_H_
