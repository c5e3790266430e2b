// The write path (embedded mode's whole, distributed mode's owner's writing
// half): a fleet's uploads are acknowledged at the durable append to its
// log, and applied behind it.
//
// Append admits an upload (validated once against the fleet's shape,
// deduplicated by (robot_id, seq) against everything the fleet received or
// holds in its log, rated, bounded by the stored-traces quota and by the
// backlog), appends its accepted traces to the fleet's log (the log port,
// fleet_log.h) as one entry under the next sequence, and returns once the entry
// is synced. Concurrent appends to one fleet are committed together: one leader
// writes every upload that queued while the previous write ran, in one synced
// log write (group commit).
//
// Appliers (a few threads shared by every fleet; a fleet's log is applied by
// one at a time, in order) run the fleet's turns of the LogApplier
// (log_applier.h): the one applier, which distributed mode's
// cluster::Materialiser runs over the replicated log too, storing each
// upload with its entry's sequence (MemoryEngine::LogPosition), so that an
// entry applied again after a crash changes nothing. Consolidation,
// forgetting and indexing happen there, off the acknowledgement. Applied
// entries are trimmed from the log.
//
// Open replays the unapplied tail of every fleet's log: nothing acknowledged
// is lost, and nothing is applied twice.
//
// Distributed mode's fleet owner (cluster::ReplicatedMemory) writes its
// fleets' replicated logs through a write path too (WritePathOptions::
// replicated), so that an upload is admitted and appended the same way in
// both modes; there the log is applied by cluster::Materialiser under the
// fleet's lease, not here: no appliers, no trims, no recovery at Open. A
// fleet's writes begin when the owner takes it (Own: the tail after its
// position is read back, as Open reads every fleet's) and end when it loses
// it (Disown); Applied says how far the owner has applied.
#ifndef FLEETMEM_SERVICES_ENGINE_WRITE_PATH_H_
#define FLEETMEM_SERVICES_ENGINE_WRITE_PATH_H_

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <thread>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "services/core/seq_set.h"
#include "services/core/types.h"
#include "services/engine/fleet_log.h"
#include "services/engine/log_applier.h"
#include "services/engine/memory_engine.h"

namespace fleetmem::engine {

struct WritePathOptions {
  // Traces a fleet's log may hold unapplied. An upload that would take the
  // backlog past it is refused with RESOURCE_EXHAUSTED naming the backlog
  // and its age (robots retry it with backoff); 0: unbounded. The backlog
  // lives in the log (on disk, about 1.1 KB per 256-d trace), not in
  // memory: the bound is how far the applier may fall behind a burst. The
  // default takes a burst of one stream for 10 s on this project's 2-core
  // machine (129,000-166,000 traces/s acknowledged, docs/performance.md,
  // fourth round) and costs up to 2.2 GB of disk per fleet at 256-d; the
  // applier catches up at its own rate (2,600-3,200 traces/s while a burst
  // drains there: minutes, during which queries do not see the backlog).
  uint64_t max_backlog_traces = 2'000'000;
  // Applier threads shared by every fleet.
  int appliers = 2;
  // Their nice value (0..19; common::MarkBackgroundThread), and so that of
  // the graph-linking threads an applier starts: 10 gives the threads that
  // answer calls about ten times the appliers' CPU share when both want it,
  // so a burst's acknowledgements and concurrent queries are not slowed by
  // applying it; the backlog takes up the difference. 0: the calls' own.
  int applier_nice = 10;
  // Log entries one applier reads and applies per turn of a fleet before it
  // trims them and lets the next fleet have a turn.
  size_t apply_batch = 64;
  // After an apply fails on the store (a full disk), its fleet's log is
  // tried again this much later; the backlog meanwhile grows to its bound.
  absl::Duration retry_interval = absl::Seconds(1);
  // Observer of the duplicates each upload had (found here, at the append,
  // so the engine's apply meets none; metrics). May be empty.
  std::function<void(std::string_view fleet_id, uint64_t duplicates)>
      on_duplicates;

  // Set: the write path of distributed mode's owner over a replicated log
  // (see above). `cut` makes an upload's accepted traces log entries: one
  // robot's run each, under an id the log deduplicates a retry by, within
  // the log's largest entry (cluster::CutUpload); INVALID_ARGUMENT, with
  // nothing appended, when a trace fits in none. The log numbers its own
  // entries (AppendOptions::above is not passed). Upload rates are not
  // checked here: the replica that receives an upload rates it.
  struct Replicated {
    std::function<absl::StatusOr<std::vector<LogPiece>>(
        std::span<const core::MemoryTrace>)>
        cut;
  };
  std::optional<Replicated> replicated;
};

absl::Status ValidateWritePathOptions(const WritePathOptions& options);

// An upload as Append admitted it.
struct Appended {
  uint64_t accepted = 0;
  uint64_t duplicates = 0;
  // The log entry holding the accepted traces (0: none, every trace was a
  // duplicate).
  uint64_t sequence = 0;
  // With Append's `track`, and an entry: what applying it did, filled in
  // before WaitApplied(sequence) returns OK (its `refused`: the engine's
  // refusal, which Append's checks make impossible; logged if it happens).
  std::shared_ptr<const AppliedRecord> applied;
};

// A fleet's log as it stands (GetStats, /metrics).
struct Backlog {
  uint64_t entries = 0;  // acknowledged, not applied yet
  uint64_t traces = 0;
  // Age of the oldest unapplied entry (0 with none).
  double oldest_seconds = 0;
  uint64_t appended_through = 0;  // last sequence acknowledged
  uint64_t applied_through = 0;   // last sequence applied
  // Why the applier waits, while it does (a store error); OK otherwise.
  absl::Status apply_error;
  // Acknowledged entries the log found damaged and passed over since it
  // opened (FleetWrites::Losses): lost, never applied.
  std::vector<LostLogEntries> lost;
  // Entries in `lost`.
  uint64_t lost_entries() const {
    uint64_t entries = 0;
    for (const LostLogEntries& range : lost) {
      entries += range.last - range.first + 1;
    }
    return entries;
  }
};

// What an operator must hear about the fleets' logs (/readyz), a line each:
// acknowledged entries lost to damage (DATA_LOSS), and logs whose applier
// waits on a store error (e.g. the disk below its reserve: acknowledged
// uploads stay unapplied, and unseen by reads, until it is resolved). Empty
// when all is well.
std::vector<std::string> BacklogWarnings(
    const std::vector<std::pair<std::string, Backlog>>& backlogs);

// Thread-safe.
class WritePath {
 public:
  // Recovers every fleet's log from `log` (the entries after the
  // position the engine holds, MemoryEngine::LogPosition) and starts the
  // appliers, which apply that tail first. `engine` and `log` must
  // outlive the write path.
  static absl::StatusOr<std::unique_ptr<WritePath>> Open(
      WritePathOptions options, MemoryEngine* engine, FleetLog* log);
  // Stop().
  ~WritePath();
  WritePath(const WritePath&) = delete;
  WritePath& operator=(const WritePath&) = delete;

  // Admits and appends `traces`, returning once they are durable in the
  // fleet's log. `fleet_id` is trusted: checked at the edge
  // (transport/upload_checks.h), not here. Errors change nothing:
  // INVALID_ARGUMENT (as MemoryEngine::Upload validates), RESOURCE_EXHAUSTED (a
  // quota, the backlog bound, a full disk), the log's error (nothing appended),
  // UNAVAILABLE after Stop. `track`: the result says what applying the
  // entry did (Appended::applied).
  absl::StatusOr<Appended> Append(std::string_view fleet_id,
                                  std::span<const core::MemoryTrace> traces,
                                  bool track = false);
  // Append for several uploads of one caller (the messages of one upload
  // stream read while the previous ones were written), in order, in one
  // group commit where they meet no other leader: one result each, as
  // Append's. An upload's refusal does not stop the others.
  std::vector<absl::StatusOr<Appended>> AppendMany(
      std::string_view fleet_id,
      std::span<const std::span<const core::MemoryTrace>> uploads,
      bool track = false);

  // Appends a call's record (ConsolidateRecord, SampleReplayRecord) to the
  // fleet's log, after every upload acknowledged before it (the same group
  // commit), and returns once it is durable: Appended::sequence is its
  // entry, and Appended::applied what applying it did, filled in before
  // WaitApplied(sequence) returns OK. The call's arguments are the
  // caller's to check first (MemoryEngine::CheckSampleReplay): what the
  // fleet's state refuses is passed when applied, the refusal in
  // AppliedRecord::refused. NOT_FOUND for a fleet with no upload
  // acknowledged; the log's error (nothing appended); UNAVAILABLE after
  // Stop.
  absl::StatusOr<Appended> AppendCall(std::string_view fleet_id,
                                      const LogRecord& call);
  // A CreateFleet's record (embedded mode), appended as the fleet's first
  // entry: ALREADY_EXISTS if the fleet exists or its log holds an entry;
  // the limits a new fleet passes (max_fleets, max_code_dimension) as for
  // its first upload. Nothing is logged on an error.
  absl::StatusOr<Appended> AppendCreate(std::string_view fleet_id,
                                        const CreateFleetRecord& create);

  // Returns once the fleet's log is applied through `sequence` (at once for
  // 0). DEADLINE_EXCEEDED at `deadline`, UNAVAILABLE after Stop,
  // RESOURCE_EXHAUSTED as soon as an apply tried after the call began is
  // refused by the store (a full disk; the entry stays durable and is
  // applied once writes resume).
  absl::Status WaitApplied(std::string_view fleet_id, uint64_t sequence,
                           absl::Time deadline);
  // WaitApplied through everything acknowledged so far (Consolidate: a call
  // sees every upload acknowledged before it).
  absl::Status WaitAppliedAll(std::string_view fleet_id, absl::Time deadline);

  // The fleet's backlog (zeros for a fleet it has not seen).
  Backlog GetBacklog(std::string_view fleet_id) const;
  // Uploads of the fleet waiting for the group commit's next write.
  size_t QueuedUploads(std::string_view fleet_id) const;
  // Every fleet's backlog, sorted by fleet (metrics).
  std::vector<std::pair<std::string, Backlog>> Backlogs() const;

  // Waits until every fleet's log is applied through what was acknowledged
  // when it is called, or until `deadline`; true if it was. A clean
  // shutdown calls it before Stop.
  bool Drain(absl::Time deadline);

  // Distributed mode's owner (WritePathOptions::replicated). Own: this
  // replica holds the fleet's lease and has applied its log through
  // `position`: its writes begin here, with the entries after `position`
  // read back as its backlog and its admitted seqs (as Open reads every
  // fleet's in embedded mode). At once if they began already.
  // FAILED_PRECONDITION for a fleet whose log holds no upload and that the
  // engine does not hold (a fleet is created by its first upload,
  // cluster::Ingest); the log's error otherwise.
  absl::Status Own(std::string_view fleet_id, uint64_t position);
  // The owner has applied the fleet's log through `sequence`.
  void Applied(std::string_view fleet_id, uint64_t sequence);
  // The fleet's lease is lost: its queued uploads are refused (UNAVAILABLE:
  // retry, the new owner admits them), its waiters woken, its state
  // forgotten. An upload a leader is appending finishes.
  void Disown(std::string_view fleet_id);

  // Stops admitting, wakes every waiter (UNAVAILABLE), and ends the appliers
  // after the entry each is applying; the rest of the logs is applied at the
  // next Open. Idempotent.
  void Stop();

 private:
  // A fleet's side of the write path: its group commit, admission state
  // and the entries of its log not applied yet.
  struct FleetWrites;
  struct Request;
  WritePath(WritePathOptions options, MemoryEngine* engine, FleetLog* log);

  // The fleet's log, made on first use; Find: null if there is none. (Held
  // by callers through a call: Disown may forget it meanwhile.)
  FleetWrites* Log(std::string_view fleet_id);
  std::shared_ptr<FleetWrites> Find(std::string_view fleet_id) const;
  absl::Status Recover();
  // A fleet the engine holds and this write path has no log of yet: its
  // log made as Recover makes it (the engine's shape and position).
  // NOT_FOUND for a fleet the engine does not hold.
  absl::StatusOr<FleetWrites*> Adopt(std::string_view fleet_id);
  // Recover for one fleet's log, whose last entry is `last`: the entries
  // after `position` (what is applied) become the fleet's backlog. True if
  // the fleet's first upload is among them (the fleet is made when applied).
  absl::StatusOr<bool> RecoverTail(FleetWrites& log, uint64_t position,
                                   uint64_t last);
  // Logs the fleet's damaged log entries: lost (DATA_LOSS) after
  // `position`, harmless at or before it.
  void ReportLosses(const std::string& fleet_id, uint64_t position);
  // AppendMany for a fleet without a log yet: the first upload with traces
  // is checked (shape, max_fleets) before the log is made.
  std::vector<absl::StatusOr<Appended>> AppendToNewFleet(
      std::string_view fleet_id,
      std::span<const std::span<const core::MemoryTrace>> uploads, bool track);
  // After Stop: refuses the `requests` still queued (UNAVAILABLE); true if
  // every one of them is done then. With log.mu held.
  bool RefuseQueued(FleetWrites& log, std::span<Request> requests);
  // Waits until every one of `requests` (queued by the caller) is done:
  // leads group commits while no one else does, follows otherwise. With
  // log.mu held.
  void Commit(FleetWrites& log, std::span<Request> requests);
  // Leads one group commit: takes the queue, Lead, then records what it
  // appended as unapplied entries and schedules the fleet's applier. With
  // log.mu held (released while Lead writes).
  void LeadQueued(FleetWrites& log);
  // The group commit's leader: admits `group`'s uploads and appends the
  // accepted ones in one log write.
  void Lead(FleetWrites& log, std::span<Request* const> group);
  struct Group;
  // Admits one upload of a group (engine/admission.h, and de-duplication
  // by (robot, seq)): its result, and its entry in `group` if it adds any.
  void Admit(FleetWrites& log, Group& group, Request& request);
  // Admit of a CreateFleet: the fleet's first entry, or ALREADY_EXISTS.
  void AdmitCreate(FleetWrites& log, Group& group, Request& request,
                   const CreateFleetRecord& create);
  // Adds an admitted upload's new traces (`accept`, `accepted` of them) to
  // `group`'s appends: one entry, or a replicated log's pieces (a cut that
  // fails refuses the upload); its robots' seqs as `trial` leaves them.
  void Stage(Group& group, Request& request, const std::vector<bool>& accept,
             uint64_t accepted,
             absl::flat_hash_map<std::string_view, core::SeqSet>& trial);
  // The robot's seqs as `group` leaves them: admitted before, or received
  // by the engine and found in the log's tail at Open.
  const core::SeqSet& SeqsOf(FleetWrites& log, Group& group,
                             const std::string& robot_id);
  void Schedule(FleetWrites& log);
  void RunApplier();
  // Applies up to apply_batch entries of the fleet (fewer after Stop, or
  // when one fails: the fleet's applier then waits retry_interval).
  void ApplyTurn(FleetWrites& log);
  // The fleet's log is applied through `sequence` (the entries through it
  // leave the backlog; a waiter on `sequence` gets `outcome`).
  void MarkApplied(FleetWrites& log, uint64_t sequence,
                   const AppliedRecord& outcome);
  // Reports a failed apply (GetStats' apply_error, waiters) and waits
  // retry_interval, or until Stop.
  void WaitToRetry(FleetWrites& log, uint64_t from, const absl::Status& status);

  const WritePathOptions options_;
  MemoryEngine* const engine_;
  FleetLog* const log_;
  LogApplier applier_;

  mutable absl::Mutex logs_mu_;
  absl::flat_hash_map<std::string, std::shared_ptr<FleetWrites>> logs_
      ABSL_GUARDED_BY(logs_mu_);
  // Fleets that exist or whose first upload is in a log (max_fleets).
  // Taken down to 0, never below: a replicated log's owner counts only the
  // fleets it made or opened, and may delete one made elsewhere (an
  // unsigned wrap refused every new fleet as over max_fleets).
  uint64_t fleets_ ABSL_GUARDED_BY(logs_mu_) = 0;

  absl::Mutex ready_mu_;
  absl::CondVar ready_cv_;
  absl::CondVar stop_cv_;  // wakes an applier waiting to retry
  std::atomic<bool> stop_{false};
  std::deque<FleetWrites*> ready_ ABSL_GUARDED_BY(ready_mu_);
  bool stopping_ ABSL_GUARDED_BY(ready_mu_) = false;
  std::vector<std::thread> appliers_;
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_WRITE_PATH_H_
