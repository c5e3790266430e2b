// The robot's durable state on its own disk (RocksDB, every write synced):
//
//   - the open segment: each observation's trace (code, place, R_in; no seq
//     yet) is recorded together with the source position, so a restarted
//     robot resumes after the last observation it recorded, and neither
//     repeats nor skips one;
//   - the upload queue (store-and-forward): sealing a segment gives its
//     traces the next sequence numbers and moves them into the queue in one
//     atomic write with the advanced seq counter, so a seq is never given
//     twice, even across crashes; traces leave the queue only after the
//     server acknowledged them (a repeat after a crash is a duplicate the
//     server drops by (robot_id, seq));
//   - each sealed trace's source position by seq, kept after its upload, so
//     that an encoder migration can re-encode what the robot observed;
//   - the counters and cursors of RobotState (robot_state.proto), written in
//     the same batch as what they count.
//
// The queue is bounded by bytes (the serialized traces of the queue and of
// the open segment). When full, FullPolicy says what happens.
//
// Thread-safe.
#ifndef FLEETMEM_CLIENTS_ROBOT_MEMORY_ROBOT_STORE_H_
#define FLEETMEM_CLIENTS_ROBOT_MEMORY_ROBOT_STORE_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "clients/robot/memory/robot_state.pb.h"
#include "fleetmem/v1/memory.pb.h"
#include "services/core/place_metrics.h"

namespace rocksdb {
class DB;
class WriteBatch;
}  // namespace rocksdb

namespace fleetmem::robot {

using state::RobotState;
using state::RobotStatus;
using state::StoredTrace;

enum class FullPolicy {
  // Default: refuse new observations (RESOURCE_EXHAUSTED) until the queue
  // drains; nothing is dropped.
  kRefuse,
  // Drop the oldest queued traces to make room (counted in traces_dropped
  // and logged by the agent).
  kDropOldest,
};

struct RobotStoreOptions {
  // Bound of queue + open segment, in serialized bytes.
  uint64_t max_bytes = 256ull << 20;
  FullPolicy full_policy = FullPolicy::kRefuse;
  // fsync every write (what makes an observation durable); tests of logic
  // only may turn it off.
  bool sync = true;
  // Disk reserve: an observation or a sealed segment is refused (UNAVAILABLE
  // "disk nearly full", nothing written) unless the filesystem of the store
  // keeps this many bytes free after it. RocksDB is never driven into
  // ENOSPC, which Debian's build answers with an assertion failure
  // (abort). Removing uploaded traces and updating counters are small and
  // not held back. 0 disables the check.
  uint64_t min_free_bytes = uint64_t{64} << 20;
  // Free bytes of the filesystem holding the store (statvfs by default;
  // tests inject).
  std::function<uint64_t()> free_bytes;
};

// Who owns a data dir.
struct RobotIdentity {
  std::string robot_id;
  std::string fleet_id;
  std::string source;
};

struct QueueInfo {
  uint64_t depth = 0;
  uint64_t bytes = 0;  // queue + open segment
  // stored_unix_ns of the oldest queued trace; 0 if the queue is empty.
  int64_t oldest_stored_unix_ns = 0;
  uint64_t open_segment = 0;
};

// Where a sealed trace came from: its seq and its observation's index in
// the source.
struct SourceIndex {
  uint64_t seq = 0;
  uint64_t index = 0;
};

class RobotStore {
 public:
  // Opens (creating if needed) the store under `dir`. A new store takes
  // `identity` with next_seq = first_seq (>= 1). FAILED_PRECONDITION if the
  // dir holds another robot's, fleet's or source's state; UNAVAILABLE /
  // INTERNAL (with RocksDB's message) if it cannot be opened.
  static absl::StatusOr<std::unique_ptr<RobotStore>> Open(
      const std::string& dir, const RobotIdentity& identity,
      const RobotStoreOptions& options);
  ~RobotStore();

  // True if Open made the store (nothing was there before).
  bool created() const { return created_; }
  // Sets next_seq of a store that has given no seq yet (after learning the
  // server's max_seq for this robot on a first start). FAILED_PRECONDITION
  // once a seq was given.
  absl::Status SetFirstSeq(uint64_t first_seq);

  RobotState state() const;
  QueueInfo queue() const;
  const RobotStoreOptions& options() const { return options_; }

  // Records observation `source_index` (== state().next_index) of the open
  // segment: `trace` without seq, and next_index = source_index + 1;
  // `update` may change other counters in the same write. Under kRefuse,
  // RESOURCE_EXHAUSTED (nothing written) while the queue is full.
  absl::Status RecordObservation(
      uint64_t source_index, const v1::MemoryTrace& trace,
      const std::function<void(RobotState&)>& update = nullptr);
  // The open segment's observations, in source order.
  absl::StatusOr<std::vector<StoredTrace>> OpenSegment() const;
  // Seals the open segment: `traces` (one per open observation, in order;
  // their seq is overwritten) get seqs next_seq, next_seq + 1, ... and move
  // to the queue; the open segment is emptied; `update` runs in the same
  // write. Under kDropOldest the oldest queued traces are dropped first if
  // the queue would exceed max_bytes. Returns the first seq given.
  // INVALID_ARGUMENT if the count does not match the open segment.
  absl::StatusOr<uint64_t> SealSegment(
      std::vector<v1::MemoryTrace> traces,
      const std::function<void(RobotState&)>& update = nullptr);

  // Up to `max` queued traces, oldest first.
  absl::StatusOr<std::vector<v1::MemoryTrace>> PeekQueue(size_t max) const;
  // Removes the queued traces with seq <= through_seq (the server
  // acknowledged them: `accepted` new, `duplicates` seen before).
  absl::Status MarkUploaded(uint64_t through_seq, uint64_t accepted,
                            uint64_t duplicates);
  // Up to `max` sealed traces with seq > after_seq and the source index of
  // each, by seq: every trace sealed since the store kept them (this
  // version on), uploaded or not. What an encoder migration re-encodes.
  absl::StatusOr<std::vector<SourceIndex>> SourceIndices(uint64_t after_seq,
                                                         size_t max) const;
  // Forgets the open segment: its observations are recorded again from its
  // first index (next_index goes back there; observations counts them
  // out). An encoder migration does so rather than seal codes of the old
  // encoder.
  absl::Status DiscardOpenSegment();
  // Changes counters only (watch cursor, refreshes, ...). The identity's
  // fleet_id may change too (an encoder migration moves the data dir to
  // the new fleet).
  absl::Status Update(const std::function<void(RobotState&)>& update);

 private:
  RobotStore(std::unique_ptr<rocksdb::DB> db, RobotStoreOptions options);
  absl::Status Load();
  // OK if writing `bytes` keeps min_free_bytes free.
  absl::Status CheckReserve(uint64_t bytes, std::string_view what) const;
  // Writes `batch` plus the state; caller holds mu_.
  absl::Status Commit(rocksdb::WriteBatch& batch, const RobotState& next)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  struct Queued {
    uint64_t bytes = 0;
    int64_t stored_unix_ns = 0;
  };

  const std::unique_ptr<rocksdb::DB> db_;
  const RobotStoreOptions options_;
  std::string path_;
  bool created_ = false;
  mutable absl::Mutex mu_;
  RobotState state_ ABSL_GUARDED_BY(mu_);
  std::map<uint64_t, Queued> queue_ ABSL_GUARDED_BY(mu_);   // by seq
  std::map<uint64_t, uint64_t> open_ ABSL_GUARDED_BY(mu_);  // index -> bytes
  uint64_t bytes_ ABSL_GUARDED_BY(mu_) = 0;
};

// The relocalisation scores of `state` (its rank histogram) as the core's
// first-correct ranks, for RecallAtK and WeightedRecall.
core::FirstCorrectRanks RelocalisationRanks(const RobotState& state);
// The same of its relocalisations re-ranked by the sequence (--sequence).
core::FirstCorrectRanks SequenceRanks(const RobotState& state);

const char* FullPolicyName(FullPolicy policy);
// "refuse" or "drop-oldest".
absl::StatusOr<FullPolicy> ParseFullPolicy(std::string_view name);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_MEMORY_ROBOT_STORE_H_
