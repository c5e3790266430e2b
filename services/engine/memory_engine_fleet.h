// Private to services/engine: MemoryEngine's per-fleet state
// (MemoryEngine::Fleet) and the helpers the engine's files share. The
// engine is split along its seams (docs/architecture.md):
//   memory_engine.cc            options, Open, the fleet table, the public
//                               write calls (Upload: a log entry's apply,
//                               Consolidate, SampleReplay), listeners;
//   memory_engine_load.cc       a fleet's load and rebuild, its place index
//                               and index snapshot, the codes held once;
//   memory_engine_apply.cc      an upload's three steps, consolidation
//                               (Algorithms 1 and 2) and the replay draw;
//   memory_engine_reads.cc      queries, stats, events and listings;
//   memory_engine_snapshots.cc  index snapshots, fleet images (export,
//                               restore) and checkpoints.
#ifndef FLEETMEM_SERVICES_ENGINE_MEMORY_ENGINE_FLEET_H_
#define FLEETMEM_SERVICES_ENGINE_MEMORY_ENGINE_FLEET_H_

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <random>
#include <span>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

#include "absl/cleanup/cleanup.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/feature_space.h"
#include "services/core/static_memory.h"
#include "services/core/validation.h"
#include "services/engine/fleet_index.h"
#include "services/engine/memory_engine.h"
#include "services/engine/pending_traces.h"

namespace fleetmem::engine {

// Seed of a fleet's generator: the configured seed mixed with a stable
// (FNV-1a) hash of the fleet id, finalised by splitmix64.
inline uint64_t FleetSeed(uint64_t seed, std::string_view fleet_id) {
  uint64_t hash = 1469598103934665603ull;
  for (unsigned char c : fleet_id) {
    hash ^= c;
    hash *= 1099511628211ull;
  }
  uint64_t z = seed ^ (hash + 0x9e3779b97f4a7c15ull);
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// Seed of the k-means of one robot's segment: the fleet's seed mixed with
// the robot id and the segment's first sequence number, so that a segment
// is clustered the same way whatever else the fleet did before it (and
// whether it was planned outside the fleet's lock or not).
inline uint64_t SegmentSeed(uint64_t fleet_seed, std::string_view robot_id,
                            uint64_t first_seq) {
  uint64_t z = FleetSeed(fleet_seed ^ first_seq, robot_id);
  z += 0x9e3779b97f4a7c15ull;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

// INVALID_ARGUMENT if `count` traces of `trace_bytes` each (at most) may be
// over `max_read_bytes` (EngineOptions::max_read_bytes), naming the most
// that fit.
inline absl::Status CheckReadSize(absl::string_view what, size_t count,
                                  size_t trace_bytes, size_t max_read_bytes) {
  const size_t fits =
      std::max<size_t>(1, max_read_bytes / std::max<size_t>(1, trace_bytes));
  if (count <= fits) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(
      what, " is ", count, " but at most ", fits, " traces of up to ",
      trace_bytes, " bytes (code and attachment) fit in one answer (",
      "max_read_bytes ", max_read_bytes, "); ask in parts"));
}

// Checks a whole upload against the fleet's shape; `meta` is null for a fleet
// that does not exist yet (its first upload then fixes the shape from
// traces[0]).
//
// `check_values` false checks the shape alone (count, encoder version and
// dimension of every trace), not each trace's ids and values: for an entry
// of a log, whose traces were checked whole where it was appended
// (WritePath::Append, or the receiving replica in distributed mode), and
// for a plan made ahead of the full check. The shape guards what memory
// and the index hold (a code of another length would overrun them).
inline absl::Status ValidateUpload(std::string_view fleet_id,
                                   std::span<const core::MemoryTrace> traces,
                                   const FleetMeta* meta, size_t max_traces,
                                   bool check_values = true) {
  if (traces.size() > max_traces) {
    return absl::InvalidArgumentError(
        absl::StrCat("upload has ", traces.size(), " traces but at most ",
                     max_traces, " are allowed per upload"));
  }
  if (traces.empty()) return absl::OkStatus();
  const size_t dimension =
      meta != nullptr ? meta->code_dimension : traces[0].code.size();
  const std::string_view encoder = meta != nullptr
                                       ? std::string_view(meta->encoder_version)
                                       : traces[0].encoder_version;
  for (size_t i = 0; i < traces.size(); ++i) {
    const core::MemoryTrace& trace = traces[i];
    const std::string what = absl::StrCat("traces[", i, "]");
    // The encoder first: another encoder is the cause, a different
    // dimension only its consequence.
    if (trace.encoder_version != encoder) {
      if (meta != nullptr) {
        return absl::InvalidArgumentError(
            absl::StrCat(what, ".encoder_version \"", trace.encoder_version,
                         "\" differs from fleet \"", V(fleet_id), "\"'s \"",
                         V(encoder), "\""));
      }
      return absl::InvalidArgumentError(absl::StrCat(
          what, ".encoder_version \"", trace.encoder_version,
          "\" differs from traces[0]'s \"", V(encoder), "\" (fleet \"",
          V(fleet_id),
          "\" is new and takes its encoder version from its first upload)"));
    }
    if (trace.code.size() != dimension) {
      if (meta != nullptr) {
        return absl::InvalidArgumentError(
            absl::StrCat(what, ".code has dimension ", trace.code.size(),
                         " but fleet \"", V(fleet_id), "\" uses ", dimension));
      }
      return absl::InvalidArgumentError(absl::StrCat(
          what, ".code has dimension ", trace.code.size(),
          " but traces[0].code has ", dimension, " (fleet \"", V(fleet_id),
          "\" is new and takes its dimension from its first upload)"));
    }
    if (!check_values) continue;
    core::TraceShape shape;
    shape.code_dimension = dimension;
    shape.encoder_version = encoder;
    shape.fleet_id = fleet_id;
    absl::Status status = core::ValidateTrace(what, trace, shape);
    if (!status.ok()) return status;
  }
  return absl::OkStatus();
}

// Event retention (EngineOptions::max_events_per_fleet): once `meta`'s
// events are more than `retained` (0: all kept), the oldest are erased by
// `mutation`.
inline void RetainEvents(size_t retained, FleetMeta& meta,
                         FleetMutation& mutation) {
  if (retained > 0 && meta.next_event_id - meta.first_event_id > retained) {
    meta.first_event_id = meta.next_event_id - retained;
    mutation.erase_events_before = meta.first_event_id;
  }
}

inline void Accumulate(const ConsolidateResult& batch,
                       ConsolidateResult* total) {
  total->consolidated_traces += batch.consolidated_traces;
  total->downsampled_traces += batch.downsampled_traces;
  total->clusters_added += batch.clusters_added;
  total->clusters_forgotten += batch.clusters_forgotten;
}

// A consolidation as ConsolidateRobot left it: applied to memory and the
// index under the exclusive lock, its store write still to be made
// (Fleet::StoreStaged, under the shared lock).
struct StagedConsolidation {
  FleetMutation mutation;
  FleetMeta meta;  // the fleet's meta once the mutation is stored
};

// What a fleet operation leaves for after the fleet lock is released.
struct Notices {
  uint64_t last_event_id = 0;  // newest durable event, 0 if none
  ConsolidateResult consolidated;
  uint64_t consolidations = 0;
  double consolidation_seconds = 0.0;
  // Consolidations not stored yet, in order (each builds on the one before).
  std::vector<StagedConsolidation> staged;
};

// A fleet's index snapshot as read from the store, before it meets the
// fleet's stored traces: the index loaded, its handle table, and
// forgetting's centroid bookkeeping still as bytes.
// Gives freed heap pages back to the system, which glibc does not do by
// itself for pages amid the heap (malloc_trim): after a load, or after a
// million codes of 1 KB each were released.
void ReturnFreedMemory();

struct LoadedSnapshot {
  // NOT_FOUND when there is none; why it is unusable otherwise.
  absl::Status status = absl::NotFoundError("no index snapshot read");
  // The index part alone (e.g. of another index kind): forgetting's
  // centroids may still be used.
  absl::Status index_status;
  uint32_t dimension = 0;
  uint64_t next_handle = 0;
  std::unique_ptr<PlaceIndex> index;
  TraceHandles handles;
  bool handles_loaded = false;  // `handles` are the snapshot's
  // What StaticMemory::SaveCentroids wrote: in the snapshot's mapped file
  // while the loading thread keeps it (from a memory image, until
  // `await_all`), else in `centroids`.
  std::span<const char> centroid_bytes;
  std::string centroids;
  // The memory image (memory_image.h) and the handles' bytes in the mapped
  // file, handed to the loading thread (ReadWithImage) for it to parse;
  // image_loaded: they are (a snapshot of format ENG3 read for that).
  std::span<const char> image;
  std::span<const char> handle_bytes;
  bool image_loaded = false;
  // `dimension` and `centroids` are read (and the checksum passed).
  bool centroids_read = false;
  double handles_seconds = 0;
  double check_seconds = 0;  // the store's checksum (IndexSnapshotBytes)
  double index_seconds = 0;
  double thread_waited_seconds = 0;  // the load's join of the reading thread
  size_t unindexed = 0;  // the loaded index's codes outside its graph
  // Set while a thread still reads the snapshot into this (the load's
  // SnapshotReader, after the clusters came from the memory image): wait
  // until `centroids_read` is set or will not be (`dimension` is set
  // then), and until the thread ended (every member set).
  std::function<void()> await_centroids;
  std::function<void()> await_all;
};

// One fleet's state. Every member but `id`, `engine`, the mutexes and
// `plan_options` is guarded by `mu`.
struct MemoryEngine::Fleet {
  Fleet(std::string fleet_id, const MemoryEngine* owner)
      : id(std::move(fleet_id)),
        engine(owner),
        memory(owner->MemoryOptionsFor(id)),
        seed(FleetSeed(memory.options().seed, id)),
        plan_options(memory.options()),
        rng(seed) {}

  // True once the fleet's first upload is durable.
  bool exists() const ABSL_SHARED_LOCKS_REQUIRED(mu) {
    return meta.code_dimension != 0;
  }

  // Rebuilds every member from the store (and the fleet's index snapshot,
  // unless `with_snapshot` is false: the index is then built from the
  // store's codes). On failure the fleet is left empty and `stale` holds
  // the error; the next mutating call retries.
  absl::Status Reload(bool with_snapshot = true)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Reloads if a previous reload failed, or without the index snapshot if
  // the index met damage in it (PlaceIndex::Damaged).
  absl::Status EnsureLoaded() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // True if the fleet's index met damage in its snapshot's file
  // (PlaceIndex::Damaged); takes `mu` shared.
  bool IndexDamaged() const ABSL_LOCKS_EXCLUDED(mu) {
    absl::ReaderMutexLock lock(&mu);
    return index.get() != nullptr && index.get()->Damaged();
  }
  // For readers: OK unless a reload failed.
  absl::Status CheckLoaded() const ABSL_SHARED_LOCKS_REQUIRED(mu);
  // `snapshot`, if given, is the fleet's index snapshot read beside the
  // store's load (ReadSnapshot); without one the index is rebuilt.
  absl::Status Rebuild(FleetRecord record, LoadedSnapshot* snapshot = nullptr)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Rebuild's steps: the fleet emptied, with `stored` as its meta; the
  // stored clusters' traces (marked with their cluster) and the pending
  // ones, for the index (DATA_LOSS for a cluster id stored twice).
  void Reset(const FleetMeta& stored) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  absl::StatusOr<std::vector<const core::MemoryTrace*>> GatherTraces(
      std::vector<core::Cluster>& clusters) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // A load from the fleet's index snapshot (written by SaveIndexSnapshot
  // at a clean shutdown or periodically while serving), read and its index
  // loaded beside the store's read (ReadSnapshot; after a read of the
  // memory image the index may still be loading: LoadedSnapshot::
  // await_all): memory restores `clusters` with forgetting's centroid
  // bookkeeping from it, meanwhile; then both
  // are reconciled with `traces`, the stored ones: what the snapshot holds
  // that the store no longer does is removed, what it lacks is added under
  // new handles (the tiered index's background thread catches up). On an
  // error before memory was touched `*restored` stays false; on one after,
  // memory is complete and only the index must be rebuilt (it is left
  // without one then).
  absl::Status LoadFromSnapshot(
      LoadedSnapshot& snapshot, std::vector<core::Cluster>& clusters,
      const std::vector<const core::MemoryTrace*>& traces, bool* restored)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Writes the index and the handles through the store (SaveIndexSnapshots);
  // `written` is the store's (MemoryStore::SaveIndexSnapshot): called once
  // nothing of the fleet is read any more, before the bytes are synced.
  absl::Status SaveIndexSnapshot(const std::function<void()>& written) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // Appends a pending trace of its robot.
  void AddPending(core::MemoryTrace trace) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // The trace with `key` in the static memory or among the pending traces.
  // Its code may be empty (ReleaseCodes): copies that leave the
  // engine go through WithCode.
  const core::MemoryTrace* FindTrace(const core::TraceKey& key) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // `trace` with its code: a static-memory trace whose code memory dropped
  // gets it from the index. INTERNAL if neither has it (a bug).
  absl::StatusOr<core::MemoryTrace> WithCode(core::MemoryTrace trace) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // WithCode of each trace without its code, in place: the index's copies
  // in one PlaceIndex::CopyCodes (one batch of its rows).
  absl::Status FillCodes(std::vector<core::MemoryTrace>& traces) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // Appends the held clusters among `cluster_ids` to mutation.put_clusters
  // with their centroids, and their traces' keys to *keys. A trace whose
  // code memory dropped goes without it: the store keeps the code it holds
  // (FleetMutation::put_clusters), so a merge reads and rewrites no code.
  void PutClusters(std::span<const uint64_t> cluster_ids,
                   FleetMutation& mutation,
                   std::vector<core::TraceKey>* keys) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // A query's matches from the index's `neighbors` (`codes`: the index's
  // copies of their codes, taken where it gave them), each trace copied
  // with its code; the query (`k`) is refused whole, INVALID_ARGUMENT,
  // when they hold more than `max_read_bytes`.
  absl::StatusOr<std::vector<PlaceMatch>> MatchesOf(
      std::span<const Neighbor> neighbors,
      std::vector<std::vector<float>>& codes, size_t k,
      size_t max_read_bytes) const ABSL_SHARED_LOCKS_REQUIRED(mu);
  // One copy of each code: frees memory's codes of those of `keys`
  // (static-memory traces) that the index keeps itself (PlaceIndex::
  // HoldsCodes: the exact, HNSW and tiered indexes do, FLANN does not).
  // Returns the codes freed.
  size_t ReleaseCodes(const std::vector<core::TraceKey>& keys)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // ReleaseCodes of every static-memory trace that still has its code
  // (the caller returns the freed pages: ReturnFreedMemory).
  size_t ReleaseAllCodes() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);

  // An upload in three steps, so that readers wait only for the last:
  // PrepareUpload checks it and builds the store mutation (shared lock); the
  // caller makes it durable (shared lock still held: the store's fsync does
  // not block queries); CommitUpload applies it to memory and consolidates
  // full segments (exclusive lock). The caller holds writer_mu throughout.
  //
  // An upload that fills a robot's segment is not stored first: CommitUpload
  // writes it together with the segment's consolidation, in one atomic
  // store write (one fsync instead of two, and the segment's traces are
  // written once, in their clusters, instead of as pending traces that the
  // consolidation then erases).
  // The three steps under writer_mu, then the consolidation's store write
  // (StoreStaged) and the index's catch-up (its back-pressure, outside the
  // fleet's lock): MemoryEngine::Upload's writes. `plan` may be null.
  absl::Status WriteUpload(std::span<const core::MemoryTrace> traces,
                           uint64_t log_position,
                           const core::ConsolidationPlan* plan,
                           UploadResult* result, Notices* notices)
      ABSL_LOCKS_EXCLUDED(mu, writer_mu);
  struct PreparedUpload {
    FleetMutation mutation;
    std::unique_ptr<PlaceIndex> new_index;  // for a new fleet
    // Some robot's pending traces reach the segment size with this upload.
    bool fills_segment = false;
    // The caller stored `mutation` before CommitUpload.
    bool stored = false;
  };
  // An upload's writes that ride on the store write of the consolidation it
  // triggered (ConsolidateRobot).
  struct CarriedUpload {
    // The upload's writes other than the consolidated robot's traces.
    FleetMutation mutation;
    // The consolidated robot's traces of this upload: never stored as
    // pending, so the consolidation erases no pending key for them.
    absl::flat_hash_set<core::TraceKey> unstored;
  };
  absl::Status PrepareUpload(std::span<const core::MemoryTrace> traces,
                             uint64_t log_position, UploadResult* result,
                             PreparedUpload* prepared)
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // PrepareUpload's steps: the limits only a direct call passes (not an
  // entry of a log), the traces not received before, and whether they fill
  // a robot's segment.
  absl::Status AdmitDirectCall(UploadQuota& quota,
                               std::span<const core::MemoryTrace> traces,
                               bool is_new);
  std::map<std::string, RobotRecord> NewTraces(
      std::span<const core::MemoryTrace> traces, UploadResult* result,
      FleetMutation& mutation) const ABSL_SHARED_LOCKS_REQUIRED(mu);
  bool FillsSegment(std::span<const core::MemoryTrace> arriving) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // `plan`, if given, is PlanAhead's for the first robot this upload
  // fills; it is used if it fits that robot's segment.
  absl::Status CommitUpload(PreparedUpload prepared, UploadResult* result,
                            Notices* notices,
                            const core::ConsolidationPlan* plan = nullptr)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // For an upload of one robot that fills its segment: the consolidation
  // plan of that segment as it stands now (k-means and downsampling), made
  // under the shared lock's snapshot but computed without any lock, so that
  // uploads of different robots cluster their segments on different cores.
  // Nothing if the upload fills no segment. Called without writer_mu; the
  // plan may be stale by the time the upload holds it (ConsolidateRobot
  // then plans again).
  std::optional<core::ConsolidationPlan> PlanAhead(
      std::span<const core::MemoryTrace> traces) ABSL_LOCKS_EXCLUDED(mu);
  // The plan of `batch`, one robot's segment, with its own seed.
  core::ConsolidationPlan Plan(
      const std::vector<core::MemoryTrace>& batch) const;
  // The store write a consolidation of `batch` starts from: `carried`'s,
  // and the batch's pending records erased.
  static FleetMutation ErasingPending(
      const std::vector<core::MemoryTrace>& batch, CarriedUpload* carried);
  // Consolidates all pending traces of `robot_id` as one batch (Algorithm 1
  // and 2) in memory and the index, and stages the outcome's store write,
  // together with `carried`'s writes if given, in notices->staged for
  // StoreStaged. On an error the fleet is reloaded from the store, which
  // holds neither, and notices->staged is emptied.
  absl::Status ConsolidateRobot(const std::string& robot_id, Notices* notices,
                                CarriedUpload* carried = nullptr,
                                const core::ConsolidationPlan* plan = nullptr)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Stores notices->staged in order under the shared lock, so that queries
  // go on while the consolidations are written (they already see them:
  // memory and the index ran ahead), then publishes the fleet's meta under
  // the exclusive lock. A failed write reloads the fleet from the store
  // (the consolidations stored before it stay) and is returned, with
  // notices' consolidation counts reset. The caller holds writer_mu, so
  // that nothing else changes the fleet meanwhile.
  absl::Status StoreStaged(Notices* notices) ABSL_LOCKS_EXCLUDED(mu);
  // Eq. 18 draw with the replay counts incremented in memory (exclusive
  // lock). `mutation` gets what must be stored and `record` the robot's new
  // record; a retry of the previous request returns its traces and leaves
  // `mutation` empty. The caller stores the mutation under the shared lock,
  // then calls FinishSample (or Reload on failure).
  // A non-zero `log_position` seeds the draw from it and stores it; a
  // `filter` draws among the traces it matches only.
  absl::StatusOr<std::vector<core::MemoryTrace>> DrawSample(
      std::string_view robot_id, size_t count, std::string_view request_id,
      uint64_t log_position, const core::ReadFilter* filter,
      FleetMutation* mutation) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  void FinishSample(FleetMutation mutation) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // DeleteTraces' change of memory, the pending traces and the index
  // (exclusive lock), and the store write that makes it durable
  // (`mutation`, with the fleet's new meta): the caller stores it, then
  // publishes the meta, or reloads on failure. On an error here the fleet
  // is reloaded and nothing is to be stored.
  // `leaves` says which traces go; `filter` names the robot and domain of
  // the pending traces' event (empty for retention's).
  absl::Status StageDelete(
      const std::function<bool(const core::MemoryTrace&)>& leaves,
      const core::TraceFilter& filter, uint64_t log_position,
      DeleteResult* result, FleetMutation* mutation)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // The traces retention deletes as of `now_ns` (the fleet's settings:
  // older than max_age_seconds, or beyond a robot's newest
  // max_traces_per_robot by seq).
  std::function<bool(const core::MemoryTrace&)> RetentionLeaves(
      int64_t now_ns) const ABSL_SHARED_LOCKS_REQUIRED(mu);
  // UpdateRewards' change of memory and the pending traces, and its store
  // write, as StageDelete.
  absl::Status StageRewards(std::span<const core::RewardUpdate> updates,
                            uint64_t log_position, RewardsResult* result,
                            FleetMutation* mutation)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Stores `mutation`, which memory shows already (readers see it while it
  // is written), under the shared lock; then publishes its meta, or
  // reloads the fleet (memory back to what the store holds) and returns the
  // store's error. The caller holds writer_mu.
  absl::Status StoreMutation(const FleetMutation& mutation)
      ABSL_LOCKS_EXCLUDED(mu);
  // The meta a log entry's apply stores: `meta` with the entry's position
  // (no change for a direct call, or an entry below the position).
  void AdvancePosition(uint64_t log_position, FleetMutation* mutation) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // The options memory consolidates with: the fleet's own settings if it
  // has any stored, else the server's.
  core::MemoryOptions OptionsOf(const FleetMeta& stored) const {
    return stored.settings ? stored.settings->memory
                           : engine->MemoryOptionsFor(id);
  }
  // Memory takes `options`, and Plan made outside the lock follows.
  void SetOptions(const core::MemoryOptions& options)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
    memory.SetOptions(options);
    absl::MutexLock lock(&plan_options_mu);
    plan_options = options;
  }
  core::MemoryOptions PlanOptions() const {
    absl::MutexLock lock(&plan_options_mu);
    return plan_options;
  }
  // The fleet's settings as they apply now: its own, or the server's.
  FleetSettings Settings() const ABSL_SHARED_LOCKS_REQUIRED(mu) {
    if (meta.settings) return *meta.settings;
    FleetSettings settings;
    settings.memory = memory.options();
    return settings;
  }
  // Sets `held` from memory (after every change of its trace count).
  void PublishHeld() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
    held.store(memory.trace_count() + pending.size(),
               std::memory_order_relaxed);
  }
  FleetStats Stats() const ABSL_SHARED_LOCKS_REQUIRED(mu);

  // Fleet is nested in MemoryEngine and so reaches its private members; these
  // helpers keep private declarations out of the public header. Fleets are
  // never removed from the map, so a returned pointer lives as long as the
  // engine.
  static Fleet* Find(const MemoryEngine& engine, std::string_view fleet_id);
  // With `admit`: RESOURCE_EXHAUSTED (limit max_fleets) instead of adding
  // a fleet beyond the limit (without: the apply of a log entry, admitted
  // before its acknowledgement).
  static absl::StatusOr<Fleet*> FindOrAdd(MemoryEngine& engine,
                                          std::string_view fleet_id,
                                          bool admit = true);
  // For readers of an existing fleet: validates `fleet_id`, finds the fleet
  // and runs `read(fleet)` under its reader lock. INVALID_ARGUMENT,
  // NOT_FOUND, or the status of a failed reload instead.
  template <typename Read>
  static auto ReadExisting(const MemoryEngine& engine,
                           std::string_view fleet_id, Read read)
      -> decltype(read(std::declval<const Fleet&>())) {
    absl::Status status = core::ValidateId("fleet_id", fleet_id);
    if (!status.ok()) return status;
    const Fleet* fleet = Find(engine, fleet_id);
    if (fleet == nullptr) return FleetNotFound(fleet_id);
    absl::ReaderMutexLock lock(&fleet->mu);
    status = fleet->CheckLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    return read(*fleet);
  }
  // Calls the fleet's listeners (the caller holds no fleet lock).
  static void Notify(MemoryEngine& engine, std::string_view fleet_id,
                     uint64_t last_event_id);

  const std::string id;
  const MemoryEngine* const engine;

  // Serialises the fleet's mutating calls from start to end, so that they
  // reach the store in the order they change memory. Taken before `mu`.
  // Writers hold `mu` exclusively only while they change memory; their
  // store writes (and fsyncs) run under `mu`'s shared lock, beside readers.
  absl::Mutex writer_mu ABSL_ACQUIRED_BEFORE(mu);
  // Serialises the fleet's index snapshots (SaveIndexSnapshots), which
  // release writer_mu before their file is synced. Taken before writer_mu.
  absl::Mutex snapshot_mu ABSL_ACQUIRED_BEFORE(writer_mu);
  mutable absl::Mutex mu;
  absl::Status stale ABSL_GUARDED_BY(mu);
  FleetMeta meta ABSL_GUARDED_BY(mu);
  core::StaticMemory memory ABSL_GUARDED_BY(mu);
  // Traces applied and awaiting their robot's consolidation.
  PendingTraces pending ABSL_GUARDED_BY(mu);
  // The largest attachment of any trace held since the fleet was loaded
  // (never shrinks): what a sample's traces may carry besides their codes.
  size_t largest_attachment ABSL_GUARDED_BY(mu) = 0;
  std::map<std::string, RobotRecord, std::less<>> robots ABSL_GUARDED_BY(mu);
  // The normalised codes of the static memory's and the pending traces
  // under handles (the read side; fleet_index.h); no index until the code
  // dimension is known.
  FleetIndex index ABSL_GUARDED_BY(mu);
  // Traces held (static memory and pending), for readers that must not
  // wait for the fleet's lock (MemoryEngine::HeldTraces).
  std::atomic<uint64_t> held{0};
  // The fleet's seed; replay draws from `rng`, and each segment's k-means
  // from a generator of its own (SegmentSeed).
  const uint64_t seed;
  // A copy of memory's options for Plan, which runs without `mu`.
  mutable absl::Mutex plan_options_mu ABSL_ACQUIRED_AFTER(mu);
  core::MemoryOptions plan_options ABSL_GUARDED_BY(plan_options_mu);
  std::mt19937_64 rng ABSL_GUARDED_BY(mu);
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_MEMORY_ENGINE_FLEET_H_
