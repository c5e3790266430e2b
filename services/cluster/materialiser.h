// Distributed mode's ownership of a fleet (docs/distributed.md): a replica
// owns a fleet while it holds the fleet's lease, and runs the one applier
// (engine::LogApplier, which embedded mode's write path runs too) over the
// fleet's log, in order, to its own MemoryEngine, each upload stored with its
// entry's sequence (MemoryEngine::LogPosition); a new owner, or one restarted,
// resumes after the position its own store holds, or restores the fleet's
// latest snapshot first when that is far ahead of it. The owner stores a
// snapshot every options.snapshot_every entries and trims the log it
// covers. Uploads are idempotent
// by (robot_id, seq) and consolidation is seeded per segment, so any
// replica that applies the same log reaches the same memory, and entries
// applied again change nothing.
//
// Fencing: before a batch of entries the owner renews its lease (when
// options.renew_interval has passed since the last renewal); a replica
// that lost it (it stopped renewing, or NATS expired it) stops
// applying that fleet at once and answers FAILED_PRECONDITION. A replica
// that finds it was stopped for longer than options.lease_ttl takes the
// leases it could not renew meanwhile as lost at once, before NATS says
// so: the replica's watches of those fleets end then.
//
// The engine it applies to must run without upload rate limits (quota
// rates 0): refusing an entry by the clock would make replicas differ.
// Rates belong to the replica that receives an upload.
#ifndef FLEETMEM_SERVICES_CLUSTER_MATERIALISER_H_
#define FLEETMEM_SERVICES_CLUSTER_MATERIALISER_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "services/cluster/cluster_ports.h"
#include "services/common/clock.h"
#include "services/core/types.h"
#include "services/engine/fleet_log.h"
#include "services/engine/log_applier.h"
#include "services/engine/memory_engine.h"

namespace fleetmem::cluster {

struct MaterialiserOptions {
  // This replica's id in the leases (its advertised address in a cluster).
  std::string replica_id;
  // Entries read and applied per step and fleet.
  size_t batch = 256;
  // A step renews the lease first once this long has passed since its last
  // renewal (0: before every step). Keep it well under the lease's
  // time-to-live (a third of it): entries are applied only within this
  // time of a successful renewal.
  absl::Duration renew_interval = absl::ZeroDuration();
  // Snapshots (with a SnapshotStore): the owner stores one of a fleet once
  // this many log entries were applied since the fleet's latest (0: never).
  uint64_t snapshot_every = 250;
  // A replica taking a fleet restores its latest snapshot, instead of
  // applying the entries it covers, when it covers at least this many more
  // entries than the replica's own store holds, and always when the log no
  // longer holds them.
  uint64_t restore_after = 256;
  // Once a snapshot is stored, the log entries it covers are trimmed
  // (engine::FleetLog::Trim), so that logs do not grow without bound.
  bool trim_log = true;
  // The leases' time-to-live. When RenewLeases finds that it did not run
  // for longer than this (the process was stopped: SIGSTOP, a frozen VM),
  // every lease it has not renewed for this long is lost here at once,
  // whatever NATS answers later (another replica has likely taken the
  // fleet, and NATS may not tell soon). Renewals that merely wait on NATS
  // (a JetStream election) keep the lease until NATS renews or refuses it,
  // so that the fleet stays served meanwhile. 0: only a refused renewal
  // loses a lease.
  absl::Duration lease_ttl = absl::ZeroDuration();
  // Reads the time for renewals, the fencing window and lease_ttl; not
  // owned (tests pass a ManualClock).
  const Clock* clock = &Clock::Real();
  // How a call's record (Consolidate, SampleReplay) is appended to the
  // fleet's log: the entry's sequence, or the log's error. Empty: to the
  // log directly. Distributed mode's owner passes its write path's
  // (engine::WritePath::AppendCall), so that a call is ordered after the
  // uploads acknowledged before it in one group commit, as in embedded
  // mode.
  std::function<absl::StatusOr<uint64_t>(std::string_view fleet_id,
                                         const engine::LogRecord& record)>
      append_call;
};

// What one step did for a fleet.
struct StepResult {
  uint64_t applied = 0;   // entries applied in this step
  uint64_t position = 0;  // the last sequence applied so far
  uint64_t revision = 0;  // the lease's revision the step ran under
  // The step began by restoring the fleet from a snapshot through this
  // entry (0: it did not).
  uint64_t restored = 0;
  // The step took a snapshot through this entry, for the writer to store
  // (0: it did not).
  uint64_t snapshot = 0;
};

// The id of the log entry an upload's traces (of one robot) become: the
// robot and its seq range, so that a retried upload of the same traces
// has the same id (JetStream stores it once). INVALID_ARGUMENT for an
// empty upload or one of several robots.
absl::StatusOr<std::string> UploadId(std::span<const core::MemoryTrace> traces);

// An upload's traces (of one robot or several) as log entries: one per
// robot and run of consecutive traces whose encoding fits in
// `max_entry_bytes` (keep it under NATS's max_payload), each under its
// UploadId. INVALID_ARGUMENT if a single trace does not fit. The owner's
// write path cuts its uploads with it (engine::WritePathOptions::
// replicated), Ingest a fleet's first.
absl::StatusOr<std::vector<engine::LogPiece>> CutUpload(
    std::span<const core::MemoryTrace> traces, size_t max_entry_bytes);

// What Ingest appended.
struct Ingested {
  uint64_t entries = 0;            // entries the log stored
  uint64_t duplicate_entries = 0;  // entries it already held (a retry)
  uint64_t traces = 0;             // traces in the stored entries
  uint64_t duplicate_traces = 0;   // ... of which in entries held already
  uint64_t last_sequence = 0;      // the log's sequence of the last entry
};

// A fleet's creation in distributed mode (the replica that receives a
// fleet's first upload, before any replica owns the fleet; every later
// upload goes through its owner's write path, engine::WritePath), and
// tests: appends the traces (of one robot or several, as a client sent
// them) to the fleet's log as CutUpload's entries and returns once the
// log holds them all.
// INVALID_ARGUMENT, with nothing appended, if a single trace does not fit.
// On a failed append the status says which entries the log holds already
// (a retry of the whole upload appends only the rest: ids repeat).
// `creates_fleet`: the receiving replica found no log for the fleet, so
// this upload fixes its shape: its first entry is appended only as the
// log's first (AppendOptions::only_first), and FAILED_PRECONDITION,
// with nothing appended, says another upload created the fleet meanwhile
// (check the upload against that one's shape, then ingest it again).
absl::StatusOr<Ingested> Ingest(engine::FleetLog& log,
                                std::string_view fleet_id,
                                std::span<const core::MemoryTrace> traces,
                                size_t max_entry_bytes,
                                bool creates_fleet = false);

// The shape every upload to the fleet must match: its first upload's (the
// first entry of its log, or its latest snapshot's once that entry may be
// trimmed), whichever replica applies it. nullopt for a fleet without a
// log. `snapshots` may be null.
absl::StatusOr<std::optional<engine::FleetShape>> FleetShapeFromLog(
    engine::FleetLog& log, SnapshotStore* snapshots, std::string_view fleet_id);

class Materialiser {
 public:
  // `log`, `leases`, `snapshots` and `engine` must outlive it;
  // `snapshots` may be null (no snapshots: new owners replay whole logs).
  Materialiser(MaterialiserOptions options, engine::FleetLog* log,
               LeaseTable* leases, SnapshotStore* snapshots,
               engine::MemoryEngine* engine);
  // Ends the snapshot writer after the snapshot it is storing, if any.
  ~Materialiser();
  Materialiser(const Materialiser&) = delete;
  Materialiser& operator=(const Materialiser&) = delete;

  // Takes or renews the fleet's lease, then applies up to options.batch
  // entries after the last one applied. FAILED_PRECONDITION when another
  // replica owns the fleet (or took it: this replica stops applying it);
  // the log's or engine's error otherwise (nothing after the failing entry
  // is applied; the next step retries it). An entry the memory refuses
  // (INVALID_ARGUMENT, FAILED_PRECONDITION) is passed; RESOURCE_EXHAUSTED
  // (a full disk) is not. No limit refuses an entry: the owner admitted it
  // (engine/admission.h). Steps run one at a time (a lock is held
  // through the calls to NATS).
  absl::StatusOr<StepResult> Step(std::string_view fleet_id);
  // Steps until the fleet's whole log as it is now is applied.
  absl::StatusOr<StepResult> CatchUp(std::string_view fleet_id);
  // The writes the owner derives from calls (distributed mode): the call
  // is appended to the fleet's log like every other write, the log is
  // applied through it, and the answer is what applying it did, so every
  // replica that applies the log does the same. FAILED_PRECONDITION if this
  // replica does not hold the fleet's lease (the caller forwards to the
  // owner); the engine's refusal as it says it (the entry is then passed on
  // every replica alike); the log's error otherwise (appended or not: a
  // retry is a new entry; SampleReplay's request_id keeps it from counting
  // twice).
  // Any call's record (Consolidate and SampleReplay below are two):
  // appended, and the log applied through it.
  absl::StatusOr<engine::AppliedRecord> Call(std::string_view fleet_id,
                                             const engine::LogRecord& record);
  absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id);
  absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view request_id, const core::ReadFilter* filter = nullptr);
  // True if this replica holds the fleet's lease (as of its last step or
  // renewal). Does not wait for a step.
  bool Owns(std::string_view fleet_id) const;
  // The fleets it holds and the last sequence applied of each.
  std::vector<std::pair<std::string, uint64_t>> Positions() const;
  // The last sequence applied of a fleet it holds (nullopt for another).
  std::optional<uint64_t> Position(std::string_view fleet_id) const;
  // A fleet held here, against its log as it was when this replica took
  // it: until `applied` reaches `end_at_take` the state here lacks writes
  // acknowledged before the take (a hand-over, a lost owner's fleet), so
  // its reads are not served from it (ReplicatedMemory::Owner answers
  // UNAVAILABLE, retried). Entries appended after the take are the usual
  // lag of an acknowledged upload. Nullopt for a fleet not held here.
  struct TakeProgress {
    uint64_t applied = 0;
    uint64_t end_at_take = 0;
    bool caught_up() const { return applied >= end_at_take; }
  };
  std::optional<TakeProgress> Progress(std::string_view fleet_id) const;

  // Returns once every snapshot taken so far is stored (or failed) and its
  // log trimmed.
  void WaitForSnapshots();

  // Renews every lease held whose renew_interval has passed, without
  // waiting for the steps (which may run long: a batch of consolidations
  // on a loaded machine): ClusterNode calls it from a thread of its own,
  // so that a fleet's lease does not expire while another fleet's step
  // runs. A lease found lost is forgotten; its fleet's next step answers
  // FAILED_PRECONDITION. Called more than lease_ttl after its last return
  // (the process was stopped), it first drops every lease not renewed
  // within lease_ttl (MaterialiserOptions::lease_ttl).
  void RenewLeases();

  // Called with a fleet's id as soon as its lease is found lost (a renewal
  // refused), from the thread that found it
  // (a step, or RenewLeases): the fleet's watches end then, not at the end
  // of an ownership round that other fleets' calls to NATS may hold up.
  // Set before the first step.
  void OnLeaseLost(std::function<void(const std::string&)> lost) {
    on_lease_lost_ = std::move(lost);
  }

  // Gives the fleet's lease up (if held) and forgets its position.
  absl::Status Release(std::string_view fleet_id);
  // The lease held on the fleet, if any.
  std::optional<Lease> lease(std::string_view fleet_id) const;

 private:
  struct Owned {
    uint64_t position = 0;  // last sequence applied
    uint64_t snapshot = 0;  // the sequence the latest snapshot covers
    uint64_t restored = 0;  // restored through this at acquisition (or 0)
  };
  // A lease this replica holds, renewed by steps and RenewLeases alike.
  struct Held {
    Lease lease;
    absl::Time renewed_at;     // of `lease`
    uint64_t position = 0;     // Owned::position as of the last step's end
    uint64_t end_at_take = 0;  // the log's last entry when it was taken
  };
  // Renews the fleet's lease if renew_interval has passed since its last
  // renewal (or `always`). FAILED_PRECONDITION once it is lost (refused, or,
  // after this replica was `stopped`, not renewed for lease_ttl; it is
  // forgotten then); NATS's error otherwise
  // (the lease is kept: the next renewal retries it). Returns when the lease
  // was last renewed.
  absl::StatusOr<absl::Time> RenewIfDue(std::string_view fleet_id, bool always,
                                        bool stopped = false)
      ABSL_LOCKS_EXCLUDED(lease_mu_);
  // Logs the loss of the fleet's lease and calls on_lease_lost_.
  void Lost(std::string_view fleet_id, const absl::Status& why)
      ABSL_LOCKS_EXCLUDED(lease_mu_);
  // At acquisition, with the lease held: restores the fleet's latest
  // snapshot if it covers enough more than `owned.position` (or the log no
  // longer holds the entries after it); learns the latest's sequence.
  absl::Status RestoreIfBehind(std::string_view fleet_id, Owned& owned);
  // Takes a snapshot through `owned.position` if snapshot_every entries
  // were applied since the latest: the fleet's image is read here, between
  // two entries, and stored by the writer thread (then the log is trimmed),
  // so that a slow or unavailable NATS does not hold up the steps and the
  // lease renewals. Failures are logged (the log keeps its entries).
  // `now`: whatever was applied since the latest (after a DeleteFleet, so
  // that the deleted fleet's data leaves JetStream).
  void SnapshotIfDue(std::string_view fleet_id, Owned& owned,
                     StepResult& result, bool now = false);
  // A snapshot read and waiting for the writer.
  struct Pending {
    SnapshotInfo info;
    std::string image;
  };
  void WriteSnapshots();
  bool HasWork() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(pending_mu_) {
    return stopping_ || !pending_.empty();
  }
  bool Idle() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(pending_mu_) {
    return stopping_ || (pending_.empty() && !writing_);
  }
  void Store(const std::string& fleet_id, const Pending& pending);
  // Takes the fleet's lease (and restores it if behind: RestoreIfBehind);
  // the fleet's state, owned from then on. `renewed_at`: when the lease was
  // taken.
  absl::StatusOr<Owned*> Take(std::string_view fleet_id, absl::Time* renewed_at)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // The fleet's state if this replica still holds its lease (renewed if
  // due: fencing) or takes it now (Take); FAILED_PRECONDITION when another
  // replica holds it.
  absl::StatusOr<Owned*> Fence(std::string_view fleet_id,
                               absl::Time* renewed_at)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  absl::StatusOr<StepResult> StepLocked(std::string_view fleet_id,
                                        uint64_t capture,
                                        engine::AppliedRecord* outcome)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Steps until the entry at `target` (or the first after it) is applied;
  // DATA_LOSS if the log ends before it. What the entry at `target` did
  // goes to `outcome` (may be null).
  absl::StatusOr<StepResult> StepThroughLocked(std::string_view fleet_id,
                                               uint64_t target,
                                               engine::AppliedRecord* outcome)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Appends a call's record (MaterialiserOptions::append_call): its
  // entry's sequence.
  absl::StatusOr<uint64_t> AppendCall(std::string_view fleet_id,
                                      const engine::LogRecord& record);

  const MaterialiserOptions options_;
  std::function<void(const std::string&)> on_lease_lost_;
  engine::FleetLog* const log_;
  LeaseTable* const leases_;
  SnapshotStore* const snapshots_;
  engine::MemoryEngine* const engine_;
  // The one applier (engine/log_applier.h), run here under the lease.
  engine::LogApplier applier_;
  mutable absl::Mutex mu_ ABSL_ACQUIRED_BEFORE(renew_mu_);
  std::map<std::string, Owned, std::less<>> owned_ ABSL_GUARDED_BY(mu_);
  // Renewals one at a time (two at once at one revision would make the
  // second look lost); held through the call to NATS.
  absl::Mutex renew_mu_ ABSL_ACQUIRED_BEFORE(lease_mu_);
  // The leases held: read by Owns, lease and Positions without waiting for
  // a step (mu_ is held through a whole step).
  mutable absl::Mutex lease_mu_;
  std::map<std::string, Held, std::less<>> held_ ABSL_GUARDED_BY(lease_mu_);
  // When RenewLeases last returned (one thread calls it: ClusterNode's
  // renewing thread).
  absl::Time renewals_ended_ = absl::InfinitePast();

  // The snapshot writer: at most one snapshot per fleet waits (a newer one
  // replaces it).
  absl::Mutex pending_mu_;
  std::map<std::string, Pending, std::less<>> pending_
      ABSL_GUARDED_BY(pending_mu_);
  bool writing_ ABSL_GUARDED_BY(pending_mu_) = false;
  bool stopping_ ABSL_GUARDED_BY(pending_mu_) = false;
  std::thread writer_;
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_MATERIALISER_H_
