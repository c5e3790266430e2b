#include "services/engine/memory_engine.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <random>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#if __has_include(<malloc.h>)
#include <malloc.h>
#endif

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
#include "services/engine/trace_handles.h"

namespace fleetmem::engine {
namespace {

// Seed of a fleet's generator: the configured seed mixed with a stable
// (FNV-1a) hash of the fleet id, finalised by splitmix64.
uint64_t FleetSeed(uint64_t seed, std::string_view fleet_id) {
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
uint64_t SegmentSeed(uint64_t fleet_seed, std::string_view robot_id,
                     uint64_t first_seq) {
  uint64_t z = FleetSeed(fleet_seed ^ first_seq, robot_id);
  z += 0x9e3779b97f4a7c15ull;
  z = (z ^ (z >> 30)) * 0xbf58476d1ce4e5b9ull;
  z = (z ^ (z >> 27)) * 0x94d049bb133111ebull;
  return z ^ (z >> 31);
}

absl::Status FleetNotFound(std::string_view fleet_id) {
  return absl::NotFoundError(
      absl::StrCat("fleet \"", V(fleet_id),
                   "\" does not exist (it is created by its first upload)"));
}

// Checks a whole upload against the fleet's shape; `meta` is null for a fleet
// that does not exist yet (its first upload then fixes the shape from
// traces[0]).
absl::Status ValidateUpload(std::string_view fleet_id,
                            std::span<const core::MemoryTrace> traces,
                            const FleetMeta* meta, size_t max_traces) {
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
    core::TraceShape shape;
    shape.code_dimension = dimension;
    shape.encoder_version = encoder;
    shape.fleet_id = fleet_id;
    absl::Status status = core::ValidateTrace(what, trace, shape);
    if (!status.ok()) return status;
  }
  return absl::OkStatus();
}

bool IsFinitePlace(const core::Place& place) {
  return std::isfinite(place.x) && std::isfinite(place.y) &&
         std::isfinite(place.z) && std::isfinite(place.yaw);
}

double PlaceDistance(const core::Place& a, const core::Place& b) {
  const double dx = a.x - b.x;
  const double dy = a.y - b.y;
  const double dz = a.z - b.z;
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

void Accumulate(const ConsolidateResult& batch, ConsolidateResult* total) {
  total->consolidated_traces += batch.consolidated_traces;
  total->downsampled_traces += batch.downsampled_traces;
  total->clusters_added += batch.clusters_added;
  total->clusters_forgotten += batch.clusters_forgotten;
}

// What a fleet operation leaves for after the fleet lock is released.
struct Notices {
  uint64_t last_event_id = 0;  // newest durable event, 0 if none
  ConsolidateResult consolidated;
  uint64_t consolidations = 0;
  double consolidation_seconds = 0.0;
};

}  // namespace

const core::MemoryOptions& MemoryEngine::MemoryOptionsFor(
    std::string_view fleet_id) const {
  auto it = options_.fleet_memory.find(fleet_id);
  return it == options_.fleet_memory.end() ? options_.memory : it->second;
}

absl::Status ValidateEngineOptions(const EngineOptions& options) {
  absl::Status status = core::ValidateMemoryOptions(options.memory);
  if (!status.ok()) return status;
  for (const auto& [fleet_id, memory] : options.fleet_memory) {
    status = core::ValidateId("fleet_memory fleet id", fleet_id);
    if (status.ok()) status = core::ValidateMemoryOptions(memory);
    if (!status.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "memory options of fleet \"", V(fleet_id), "\": ", status.message()));
    }
  }
  const std::pair<const char*, size_t> positive[] = {
      {"segment_size", options.segment_size},
      {"max_traces_per_upload", options.max_traces_per_upload},
      {"max_sample_count", options.max_sample_count},
      {"max_query_k", options.max_query_k},
      {"max_events_per_read", options.max_events_per_read},
  };
  for (const auto& [name, value] : positive) {
    if (value == 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("engine option ", name, " must be at least 1"));
    }
  }
  return ValidateQuotaOptions(options.limits);
}

namespace {

// Gives freed heap pages back to the system, which glibc does not do by
// itself for pages amid the heap: after a load dropped a million codes of
// 1 KB each (ReleaseCodes).
void ReturnFreedMemory() {
#if defined(__GLIBC__)
  malloc_trim(0);
#endif
}

// Runs `first` on this thread and `second` beside it on another one when
// `items` makes that pay off (a restart: each is seconds long at 1,000,000
// traces), else one after the other; returns once both are done. `first`
// may be empty.
void RunBeside(const std::function<void()>& first, size_t items,
               const std::function<void()>& second) {
  // A second thread pays off from about this many items.
  constexpr size_t kParallelFrom = 10'000;
  std::thread beside;
  if (first && items >= kParallelFrom) {
    try {
      beside = std::thread(second);
    } catch (const std::system_error&) {
      // No thread: one after the other.
    }
  }
  if (first) first();
  if (beside.joinable()) {
    beside.join();
  } else {
    second();
  }
}

// Version of the engine's part of an index snapshot.
constexpr uint32_t kIndexSnapshotFormat = 0x454e4731;  // "ENG1"

// Stored traces whose codes a reconciled snapshot must hold as the store
// does (a sample: a trace's code never changes under its key, so a
// difference means the snapshot is of another history of the fleet).
constexpr size_t kCodesCheckedOnLoad = 1024;

// A fleet's index snapshot as read from the store, before it meets the
// fleet's stored traces: the index loaded, its handle table, and
// forgetting's centroid bookkeeping still as bytes.
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
  std::string centroids;  // what StaticMemory::SaveCentroids wrote
  double handles_seconds = 0;
  double index_seconds = 0;
};

// Reads `fleet_id`'s index snapshot through `store` and loads its index
// (made by `factory` for the snapshot's dimension). Needs nothing of the
// fleet, so it runs beside the store's LoadFleet (each is seconds long at
// 1,000,000 traces).
LoadedSnapshot ReadSnapshot(MemoryStore& store,
                            const PlaceIndexFactory& factory,
                            std::string_view fleet_id) {
  LoadedSnapshot loaded;
  const absl::Time start = absl::Now();
  loaded.status = store.ReadIndexSnapshot(
      fleet_id, [&](std::span<const char> bytes) -> absl::Status {
        core::ByteReader in(bytes);
        uint32_t format = 0;
        if (!in.Get(&format) || format != kIndexSnapshotFormat ||
            !in.Get(&loaded.dimension) || loaded.dimension == 0 ||
            !in.Get(&loaded.next_handle)) {
          return absl::DataLossError("bad header");
        }
        absl::Status handles = loaded.handles.Load(in, loaded.next_handle);
        if (!handles.ok()) return handles;
        loaded.handles_seconds = absl::ToDoubleSeconds(absl::Now() - start);
        uint64_t centroid_size = 0;
        std::span<const char> centroid_bytes;
        if (!in.Get(&centroid_size) ||
            !in.GetSpan(centroid_size, &centroid_bytes)) {
          return absl::DataLossError("truncated centroids");
        }
        loaded.centroids.assign(centroid_bytes.begin(), centroid_bytes.end());
        loaded.index = factory(loaded.dimension);
        if (loaded.index == nullptr) {
          return absl::InternalError("no index made");
        }
        const absl::Time index_start = absl::Now();
        absl::Status status = loaded.index->Load(in);
        loaded.index_seconds = absl::ToDoubleSeconds(absl::Now() - index_start);
        if (status.ok() && (loaded.index->size() != loaded.handles.size() ||
                            in.remaining() != 0)) {
          status = absl::DataLossError("the index does not match its handles");
        }
        loaded.index_status = status;
        return absl::OkStatus();
      });
  if (!loaded.status.ok() || !loaded.index_status.ok()) loaded.index.reset();
  return loaded;
}

}  // namespace

// One fleet's state. Every member but `id`, `engine` and the two mutexes is
// guarded by `mu`.
struct MemoryEngine::Fleet {
  Fleet(std::string fleet_id, const MemoryEngine* owner)
      : id(std::move(fleet_id)),
        engine(owner),
        memory(owner->MemoryOptionsFor(id)),
        seed(FleetSeed(memory.options().seed, id)),
        rng(seed) {}

  // True once the fleet's first upload is durable.
  bool exists() const ABSL_SHARED_LOCKS_REQUIRED(mu) {
    return meta.code_dimension != 0;
  }

  // Rebuilds every member from the store. On failure the fleet is left empty
  // and `stale` holds the error; the next mutating call retries.
  absl::Status Reload() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Reloads if a previous reload failed.
  absl::Status EnsureLoaded() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // For readers: OK unless a reload failed.
  absl::Status CheckLoaded() const ABSL_SHARED_LOCKS_REQUIRED(mu);
  // `snapshot`, if given, is the fleet's index snapshot read beside the
  // store's load (ReadSnapshot); without one the index is rebuilt.
  absl::Status Rebuild(FleetRecord record, LoadedSnapshot* snapshot = nullptr)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Adds `traces` to the index under new handles. `meanwhile`, if given,
  // runs on this thread while another thread fills the index (a restart:
  // memory restores its clusters and the index copies the codes, each
  // seconds long at 1,000,000 traces); the traces' codes must not change
  // or move meanwhile.
  // `on_load`: the adds of a load, never held up by the index's
  // back-pressure (PlaceIndex::AddNormalizedOnLoad).
  absl::Status IndexTraces(const std::vector<const core::MemoryTrace*>& traces,
                           const std::function<void()>& meanwhile = nullptr,
                           bool on_load = false)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // A load from the fleet's index snapshot (written by SaveIndexSnapshot
  // at a clean shutdown or periodically while serving), read and its index
  // loaded beside the store's read (ReadSnapshot): memory restores
  // `clusters` with forgetting's centroid bookkeeping from it; then both
  // are reconciled with `traces`, the stored ones: what the snapshot holds
  // that the store no longer does is removed, what it lacks is added under
  // new handles (the tiered index's background thread catches up). On an
  // error before memory was touched `*restored` stays false; on one after,
  // memory is complete and only the index must be rebuilt. The index and
  // the handles change only on success.
  absl::Status LoadFromSnapshot(
      LoadedSnapshot snapshot, std::vector<core::Cluster>& clusters,
      const std::vector<const core::MemoryTrace*>& traces, bool* restored)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Writes the index and the handles through the store (SaveIndexSnapshots);
  // `written` is the store's (MemoryStore::SaveIndexSnapshot): called once
  // nothing of the fleet is read any more, before the bytes are synced.
  absl::Status SaveIndexSnapshot(const std::function<void()>& written) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  absl::Status UnindexTraces(const std::vector<core::TraceKey>& keys)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
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
  absl::Status FillCodes(std::vector<core::MemoryTrace>& traces) const
      ABSL_SHARED_LOCKS_REQUIRED(mu);
  // One copy of each code: frees memory's codes of those of `keys`
  // (static-memory traces) that the index keeps itself (PlaceIndex::
  // HoldsCodes: the exact, HNSW and tiered indexes do, FLANN does not).
  // Returns the codes freed.
  size_t ReleaseCodes(const std::vector<core::TraceKey>& keys)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // ReleaseCodes of every static-memory trace that still has its code,
  // then the freed pages go back to the system.
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
  // Consolidates all pending traces of `robot_id` as one batch (Algorithm 1
  // and 2) and persists the outcome in one mutation, together with
  // `carried`'s writes if given. On a failed write the fleet is reloaded
  // from the store, which then holds neither.
  absl::Status ConsolidateRobot(const std::string& robot_id, Notices* notices,
                                CarriedUpload* carried = nullptr,
                                const core::ConsolidationPlan* plan = nullptr)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Eq. 18 draw with the replay counts incremented in memory (exclusive
  // lock). `mutation` gets what must be stored and `record` the robot's new
  // record; a retry of the previous request returns its traces and leaves
  // `mutation` empty. The caller stores the mutation under the shared lock,
  // then calls FinishSample (or Reload on failure).
  // A non-zero `log_position` seeds the draw from it and stores it.
  absl::StatusOr<std::vector<core::MemoryTrace>> DrawSample(
      std::string_view robot_id, size_t count, std::string_view request_id,
      uint64_t log_position, FleetMutation* mutation)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  void FinishSample(FleetMutation mutation) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu);
  // Sets `held` from memory (after every change of its trace count).
  void PublishHeld() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
    held.store(memory.trace_count() + pending_position.size(),
               std::memory_order_relaxed);
  }
  FleetStats Stats() const ABSL_SHARED_LOCKS_REQUIRED(mu);

  // Fleet is nested in MemoryEngine and so reaches its private members; these
  // helpers keep private declarations out of the public header. Fleets are
  // never removed from the map, so a returned pointer lives as long as the
  // engine.
  static Fleet* Find(const MemoryEngine& engine, std::string_view fleet_id);
  // RESOURCE_EXHAUSTED (limit max_fleets) instead of adding a fleet beyond
  // the limit.
  static absl::StatusOr<Fleet*> FindOrAdd(MemoryEngine& engine,
                                          std::string_view fleet_id);
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
  // Pending traces per robot, in arrival order. A robot's vector only grows
  // until it is consolidated as a whole, so positions in it are stable.
  std::map<std::string, std::vector<core::MemoryTrace>, std::less<>> pending
      ABSL_GUARDED_BY(mu);
  absl::flat_hash_map<core::TraceKey, size_t> pending_position
      ABSL_GUARDED_BY(mu);
  // Pending traces per domain (statistics without walking the traces).
  std::map<std::string, uint64_t, std::less<>> pending_by_domain
      ABSL_GUARDED_BY(mu);
  std::map<std::string, RobotRecord, std::less<>> robots ABSL_GUARDED_BY(mu);
  // Index of the normalised codes of the static memory's and the pending
  // traces under handles; null until the code dimension is known.
  std::unique_ptr<PlaceIndex> index ABSL_GUARDED_BY(mu);
  TraceHandles handles ABSL_GUARDED_BY(mu);
  uint64_t next_handle ABSL_GUARDED_BY(mu) = 1;
  // Changes to what an index snapshot holds (the index, the handles,
  // forgetting's centroids) since the fleet was loaded, and their count
  // when the store's snapshot last matched them (nullopt: it does not).
  uint64_t snapshot_changes ABSL_GUARDED_BY(mu) = 0;
  std::optional<uint64_t> snapshot_saved_at ABSL_GUARDED_BY(mu);
  // Traces held (static memory and pending), for readers that must not
  // wait for the fleet's lock (MemoryEngine::HeldTraces).
  std::atomic<uint64_t> held{0};
  // The fleet's seed; replay draws from `rng`, and each segment's k-means
  // from a generator of its own (SegmentSeed).
  const uint64_t seed;
  std::mt19937_64 rng ABSL_GUARDED_BY(mu);
};

absl::Status MemoryEngine::Fleet::Reload() {
  const absl::Time start = absl::Now();
  // The index snapshot is read and its index loaded on a second thread
  // while this one reads the fleet's traces.
  LoadedSnapshot snapshot;
  auto read_snapshot = [&] {
    snapshot = ReadSnapshot(*engine->store_, engine->index_factory_, id);
  };
  std::thread beside;
  try {
    beside = std::thread(read_snapshot);
  } catch (const std::system_error&) {
    // No thread: one after the other.
  }
  absl::StatusOr<FleetRecord> record = engine->store_->LoadFleet(id);
  if (beside.joinable()) {
    beside.join();
  } else {
    read_snapshot();
  }
  const absl::Time read = absl::Now();
  absl::Status status =
      record.ok() ? Rebuild(*std::move(record), &snapshot) : record.status();
  if (status.ok() && exists()) {
    FLEETMEM_LOG(kInfo) << "fleet \"" << id
                        << "\" loaded: " << memory.trace_count()
                        << " traces in " << memory.clusters().size()
                        << " clusters, " << pending_position.size()
                        << " pending; store read "
                        << absl::ToDoubleSeconds(read - start)
                        << " s, memory and index "
                        << absl::ToDoubleSeconds(absl::Now() - read) << " s";
  }
  if (!status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\" could not be reloaded: " << status;
    Rebuild(FleetRecord{}).IgnoreError();
    stale = status;
    return status;
  }
  stale = absl::OkStatus();
  PublishHeld();
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::EnsureLoaded() {
  if (stale.ok()) return absl::OkStatus();
  return Reload();
}

absl::Status MemoryEngine::Fleet::CheckLoaded() const {
  if (stale.ok()) return absl::OkStatus();
  return absl::UnavailableError(
      absl::StrCat("fleet \"", id, "\" is not loaded after a storage error (",
                   stale.message(), "); retry later"));
}

absl::Status MemoryEngine::Fleet::Rebuild(FleetRecord record,
                                          LoadedSnapshot* snapshot) {
  meta = record.meta;
  memory = core::StaticMemory(engine->MemoryOptionsFor(id));
  pending.clear();
  pending_position.clear();
  pending_by_domain.clear();
  robots.clear();
  index.reset();
  handles.Clear();
  next_handle = 1;
  snapshot_changes = 0;
  snapshot_saved_at.reset();
  if (meta.code_dimension == 0) {
    if (!record.clusters.empty() || !record.pending.empty()) {
      return absl::DataLossError(absl::StrCat(
          "fleet \"", id, "\" has stored traces but no code dimension"));
    }
    return absl::OkStatus();
  }
  for (core::MemoryTrace& trace : record.pending) AddPending(std::move(trace));
  for (RobotRecord& robot : record.robots) {
    std::string robot_id = robot.robot_id;
    robots[robot_id] = std::move(robot);
  }
  index = engine->index_factory_(meta.code_dimension);
  if (index == nullptr) {
    return absl::InternalError(
        absl::StrCat("the index factory made no index for fleet \"", id, "\""));
  }
  // The traces stay in their clusters' vectors when the clusters move into
  // memory, so the index can read them while memory restores.
  std::vector<const core::MemoryTrace*> traces;
  absl::flat_hash_set<uint64_t> cluster_ids;
  cluster_ids.reserve(record.clusters.size());
  for (core::Cluster& cluster : record.clusters) {
    if (!cluster_ids.insert(cluster.id).second) {
      return absl::DataLossError(absl::StrCat("fleet \"", id, "\" has cluster ",
                                              cluster.id, " twice"));
    }
    for (core::MemoryTrace& trace : cluster.traces) {
      trace.cluster_id = cluster.id;
      traces.push_back(&trace);
    }
  }
  for (const auto& [robot_id, robot_pending] : pending) {
    for (const core::MemoryTrace& trace : robot_pending) {
      traces.push_back(&trace);
    }
  }
  bool restored = false;
  if (!traces.empty()) {
    const absl::Time start = absl::Now();
    absl::Status status =
        snapshot == nullptr
            ? absl::NotFoundError("no index snapshot read")
            : LoadFromSnapshot(std::move(*snapshot), record.clusters, traces,
                               &restored);
    if (status.ok()) {
      FLEETMEM_LOG(kInfo) << "fleet \"" << id
                          << "\": loaded from its index snapshot in "
                          << absl::ToDoubleSeconds(absl::Now() - start) << " s";
      ReleaseAllCodes();
      return status;
    }
    // No snapshot is the normal case after a crash or a first start.
    if (absl::IsNotFound(status)) {
      FLEETMEM_LOG(kInfo) << "fleet \"" << id << "\": rebuilding the index ("
                          << status << ")";
    } else {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << id
          << "\": rebuilding the index, its snapshot is unusable: " << status;
    }
  }
  absl::Status status =
      restored ? IndexTraces(traces) : IndexTraces(traces, [&] {
        for (core::Cluster& cluster : record.clusters) {
          memory.Restore(std::move(cluster));
        }
      });
  if (status.ok()) ReleaseAllCodes();
  return status;
}

size_t MemoryEngine::Fleet::ReleaseCodes(
    const std::vector<core::TraceKey>& keys) {
  if (index == nullptr || keys.empty()) return 0;
  std::vector<uint64_t> ids;
  std::vector<const core::TraceKey*> indexed;
  ids.reserve(keys.size());
  indexed.reserve(keys.size());
  for (const core::TraceKey& key : keys) {
    const uint64_t handle = handles.Find(key);
    if (handle == 0) continue;
    ids.push_back(handle);
    indexed.push_back(&key);
  }
  const std::vector<bool> held = index->HoldsCodes(ids);
  size_t released = 0;
  for (size_t i = 0; i < ids.size(); ++i) {
    if (held[i] && memory.DropCode(*indexed[i])) ++released;
  }
  return released;
}

size_t MemoryEngine::Fleet::ReleaseAllCodes() {
  std::vector<core::TraceKey> keys;
  for (const auto& [cluster_id, cluster] : memory.clusters()) {
    for (const core::MemoryTrace& trace : cluster.traces) {
      if (!trace.code.empty()) keys.push_back(trace.key());
    }
  }
  const size_t released = ReleaseCodes(keys);
  // Large releases leave holes amid the heap that glibc keeps.
  if (released >= 10'000) ReturnFreedMemory();
  return released;
}

absl::StatusOr<core::MemoryTrace> MemoryEngine::Fleet::WithCode(
    core::MemoryTrace trace) const {
  if (!trace.code.empty()) return trace;
  const uint64_t handle = handles.Find(trace.key());
  if (handle == 0 || index == nullptr ||
      !index->CopyCode(handle, &trace.code)) {
    return absl::InternalError(absl::StrCat(
        "fleet \"", id, "\": the code of trace (\"", trace.robot_id, "\", ",
        trace.seq, ") is neither in memory nor in the index"));
  }
  return trace;
}

absl::Status MemoryEngine::Fleet::FillCodes(
    std::vector<core::MemoryTrace>& traces) const {
  for (core::MemoryTrace& trace : traces) {
    if (!trace.code.empty()) continue;
    absl::StatusOr<core::MemoryTrace> filled = WithCode(std::move(trace));
    if (!filled.ok()) return filled.status();
    trace = *std::move(filled);
  }
  return absl::OkStatus();
}

void MemoryEngine::Fleet::AddPending(core::MemoryTrace trace) {
  std::vector<core::MemoryTrace>& robot_pending = pending[trace.robot_id];
  pending_position[trace.key()] = robot_pending.size();
  ++pending_by_domain[trace.domain];
  robot_pending.push_back(std::move(trace));
}

const core::MemoryTrace* MemoryEngine::Fleet::FindTrace(
    const core::TraceKey& key) const {
  if (const core::MemoryTrace* trace = memory.Find(key)) return trace;
  auto position = pending_position.find(key);
  if (position == pending_position.end()) return nullptr;
  return &pending.find(key.robot_id)->second[position->second];
}

absl::Status MemoryEngine::Fleet::IndexTraces(
    const std::vector<const core::MemoryTrace*>& traces,
    const std::function<void()>& meanwhile, bool on_load) {
  if (traces.empty()) {
    if (meanwhile) meanwhile();
    return absl::OkStatus();
  }
  if (index == nullptr) {
    return absl::InternalError(absl::StrCat("fleet \"", id, "\" has no index"));
  }
  std::vector<uint64_t> ids;
  std::vector<std::span<const float>> codes;
  ids.reserve(traces.size());
  codes.reserve(traces.size());
  for (const core::MemoryTrace* trace : traces) {
    ids.push_back(next_handle++);
    codes.push_back(trace->code);
  }
  absl::Status status;
  RunBeside(meanwhile, traces.size(), [&] {
    status = on_load ? index->AddNormalizedOnLoad(ids, codes)
                     : index->AddNormalized(ids, codes);
  });
  ++snapshot_changes;
  if (!status.ok()) return status;
  handles.Reserve(handles.size() + traces.size());
  for (size_t i = 0; i < traces.size(); ++i) {
    handles.Assign(traces[i]->key(), ids[i]);
  }
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::SaveIndexSnapshot(
    const std::function<void()>& written) const {
  return engine->store_->SaveIndexSnapshot(
      id,
      [this](core::ByteWriter& out) {
        out.Put<uint32_t>(kIndexSnapshotFormat);
        out.Put<uint32_t>(meta.code_dimension);
        out.Put<uint64_t>(next_handle);
        handles.Save(out);
        // Forgetting's centroid bookkeeping, length first so that a load
        // can hand it to memory while the index reads what follows.
        core::ByteWriter counter([](std::span<const char>) {});
        memory.SaveCentroids(counter);
        out.Put<uint64_t>(counter.written());
        memory.SaveCentroids(out);
        return index->Save(out);
      },
      written);
}

absl::Status MemoryEngine::Fleet::LoadFromSnapshot(
    LoadedSnapshot snapshot, std::vector<core::Cluster>& clusters,
    const std::vector<const core::MemoryTrace*>& traces, bool* restored) {
  if (!snapshot.status.ok()) return snapshot.status;
  if (snapshot.dimension != meta.code_dimension) {
    return absl::DataLossError(
        absl::StrCat("the snapshot's codes have ", snapshot.dimension,
                     " dimensions, the fleet's ", meta.code_dimension));
  }
  std::unique_ptr<PlaceIndex> loaded = std::move(snapshot.index);
  TraceHandles& saved = snapshot.handles;
  const absl::Time memory_start = absl::Now();
  size_t centroids_reconciled = 0;
  core::ByteReader centroids(snapshot.centroids);
  absl::Status kept_centroids =
      memory.RestoreAll(std::move(clusters), centroids, &centroids_reconciled);
  *restored = true;
  if (!kept_centroids.ok()) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << id
                           << "\": forgetting's centroid graph rebuilt: "
                           << kept_centroids;
  }
  const double memory_seconds =
      absl::ToDoubleSeconds(absl::Now() - memory_start);
  absl::Status status = snapshot.index_status;
  if (!status.ok()) return status;

  // Reconcile with the store: traces stored since the snapshot are added,
  // traces forgotten or downsampled since are removed.
  const absl::Time reconcile_start = absl::Now();
  std::vector<const core::MemoryTrace*> missing;
  std::vector<const core::MemoryTrace*> kept;
  kept.reserve(std::min(traces.size(), saved.size()));
  for (const core::MemoryTrace* trace : traces) {
    (saved.contains(trace->key()) ? kept : missing).push_back(trace);
  }
  // A sample of the kept traces, spread over all of them, must have the
  // codes the store has.
  std::vector<float> code;
  const size_t step = std::max<size_t>(1, kept.size() / kCodesCheckedOnLoad);
  for (size_t i = 0; i < kept.size(); i += step) {
    const core::MemoryTrace& trace = *kept[i];
    if (!loaded->CopyCode(saved.Find(trace.key()), &code) ||
        code != trace.code) {
      return absl::DataLossError(
          absl::StrCat("the snapshot's code of trace (\"", trace.robot_id,
                       "\", ", trace.seq, ") differs from the store's"));
    }
  }
  std::vector<uint64_t> gone;
  if (kept.size() < saved.size()) {
    absl::flat_hash_set<core::TraceKey> stored;
    stored.reserve(traces.size());
    for (const core::MemoryTrace* trace : traces) stored.insert(trace->key());
    saved.ForEach(
        [&](uint64_t handle, std::string_view robot_id, uint64_t seq) {
          if (!stored.contains(core::TraceKey{std::string(robot_id), seq})) {
            gone.push_back(handle);
          }
        });
  }
  status = loaded->Remove(gone);
  if (!status.ok()) return status;
  for (uint64_t handle : gone) saved.EraseHandle(handle);
  index = std::move(loaded);
  handles = std::move(saved);
  next_handle = snapshot.next_handle;
  if (!missing.empty()) {
    status = IndexTraces(missing, nullptr, /*on_load=*/true);
    if (!status.ok()) {
      index = engine->index_factory_(meta.code_dimension);
      handles.Clear();
      next_handle = 1;
      return status;
    }
  }
  snapshot_changes = 0;
  if (missing.empty() && gone.empty() && centroids_reconciled == 0) {
    snapshot_saved_at = 0;  // the snapshot on disk is this state
  }
  FLEETMEM_LOG(kInfo) << "fleet \"" << id
                      << "\": index snapshot reconciled: " << kept.size()
                      << " codes kept, " << missing.size() << " added, "
                      << gone.size() << " removed; " << centroids_reconciled
                      << " centroids changed (handles "
                      << snapshot.handles_seconds << " s and index "
                      << snapshot.index_seconds
                      << " s beside the store's read, memory " << memory_seconds
                      << " s, reconciling "
                      << absl::ToDoubleSeconds(absl::Now() - reconcile_start)
                      << " s)";
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::UnindexTraces(
    const std::vector<core::TraceKey>& keys) {
  std::vector<uint64_t> ids;
  for (const core::TraceKey& key : keys) {
    const uint64_t handle = handles.Erase(key);
    if (handle != 0) ids.push_back(handle);
  }
  if (ids.empty() || index == nullptr) return absl::OkStatus();
  ++snapshot_changes;
  return index->Remove(ids);
}

absl::Status MemoryEngine::Fleet::PrepareUpload(
    std::span<const core::MemoryTrace> traces, uint64_t log_position,
    UploadResult* result, PreparedUpload* prepared) {
  absl::Status status = CheckLoaded();
  if (!status.ok()) return status;
  const bool is_new = !exists();
  status = ValidateUpload(id, traces, is_new ? nullptr : &meta,
                          engine->options_.max_traces_per_upload);
  if (!status.ok()) return status;
  if (traces.empty()) return absl::OkStatus();
  UploadQuota& quota = *engine->quota_;
  if (is_new) {
    status = quota.AdmitDimension(id, traces[0].code.size());
    if (!status.ok()) return status;
  }
  // Rates refuse by the clock: only a direct call is rated. An entry of a
  // log (log_position != 0) was rated when it was appended (WritePath, or
  // the receiving replica in distributed mode), and applying it again after
  // a restart must not be refused.
  if (log_position == 0) {
    status = quota.AdmitRates(id, traces);
    if (!status.ok()) return status;
  }

  // Duplicates are seqs already received or repeated within this upload:
  // inserting into a copy of the robot's SeqSet detects both.
  FleetMutation& mutation = prepared->mutation;
  std::map<std::string, RobotRecord> changed_robots;
  for (const core::MemoryTrace& trace : traces) {
    auto [it, inserted] = changed_robots.try_emplace(trace.robot_id);
    RobotRecord& record = it->second;
    if (inserted) {
      auto known = robots.find(trace.robot_id);
      if (known != robots.end()) {
        record = known->second;
      } else {
        record.robot_id = trace.robot_id;
      }
    }
    if (!record.received.Insert(trace.seq)) {
      ++result->duplicates;
      continue;
    }
    core::MemoryTrace accepted = trace;
    accepted.replay_count = 0;
    accepted.cluster_id = 0;
    mutation.put_pending.push_back(std::move(accepted));
  }
  result->accepted = mutation.put_pending.size();
  if (mutation.put_pending.empty()) return absl::OkStatus();
  status = quota.AdmitStored(id, memory.trace_count() + pending_position.size(),
                             mutation.put_pending.size());
  if (!status.ok()) {
    *result = UploadResult{};
    mutation = FleetMutation{};
    return status;
  }
  for (auto& [robot_id, record] : changed_robots) {
    auto known = robots.find(robot_id);
    const uint64_t before =
        known == robots.end() ? 0 : known->second.received.size();
    if (record.received.size() != before) mutation.put_robots.push_back(record);
  }

  absl::flat_hash_map<std::string_view, size_t> arriving;
  for (const core::MemoryTrace& trace : mutation.put_pending) {
    ++arriving[trace.robot_id];
  }
  for (const auto& [robot_id, count] : arriving) {
    auto held = pending.find(robot_id);
    const size_t before = held == pending.end() ? 0 : held->second.size();
    if (before + count >= engine->options_.segment_size) {
      prepared->fills_segment = true;
    }
  }

  if (is_new) {
    mutation.put_meta = true;
    mutation.meta = meta;
    mutation.meta.code_dimension = static_cast<uint32_t>(traces[0].code.size());
    mutation.meta.encoder_version = traces[0].encoder_version;
    prepared->new_index = engine->index_factory_(mutation.meta.code_dimension);
    if (prepared->new_index == nullptr) {
      mutation = FleetMutation{};
      return absl::InternalError(absl::StrCat(
          "the index factory made no index for fleet \"", id, "\""));
    }
  }
  if (log_position > meta.log_position) {
    if (!mutation.put_meta) mutation.meta = meta;
    mutation.put_meta = true;
    mutation.meta.log_position = log_position;
  }
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::CommitUpload(
    PreparedUpload prepared, UploadResult* result, Notices* notices,
    const core::ConsolidationPlan* plan) {
  FleetMutation& mutation = prepared.mutation;
  const bool stored = prepared.stored;
  // Not stored yet: memory runs ahead of the store until the write below,
  // under the exclusive lock, and a failure reloads the fleet.
  CarriedUpload carried;
  if (!stored) {
    carried.mutation.put_meta = mutation.put_meta;
    carried.mutation.meta = mutation.meta;
    carried.mutation.put_robots = mutation.put_robots;
  }
  if (mutation.put_meta) meta = mutation.meta;
  if (prepared.new_index != nullptr) index = std::move(prepared.new_index);
  for (RobotRecord& record : mutation.put_robots) {
    std::string robot_id = record.robot_id;
    robots[robot_id] = std::move(record);
  }
  std::vector<core::TraceKey> fresh_keys;
  fresh_keys.reserve(mutation.put_pending.size());
  for (core::MemoryTrace& trace : mutation.put_pending) {
    fresh_keys.push_back(trace.key());
    AddPending(std::move(trace));
  }
  // Pending traces are searchable at once (a robot relocalises against what
  // the fleet uploaded a moment ago, not only what is consolidated).
  std::vector<const core::MemoryTrace*> fresh;
  fresh.reserve(fresh_keys.size());
  for (const core::TraceKey& key : fresh_keys) fresh.push_back(FindTrace(key));
  absl::Status status = IndexTraces(fresh);
  if (!status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\": index update failed, rebuilding: " << status;
    absl::Status reloaded = Reload();
    if (!stored) {
      return absl::InternalError(absl::StrCat(
          "fleet \"", id, "\": index update failed (", status.message(),
          "); nothing of this upload was stored"));
    }
    if (!reloaded.ok()) return reloaded;
  }

  std::vector<std::string> full;
  for (const auto& [robot_id, robot_pending] : pending) {
    if (robot_pending.size() >= engine->options_.segment_size) {
      full.push_back(robot_id);
    }
  }
  if (!stored) {
    const std::string carrier = full.empty() ? std::string() : full.front();
    for (const core::TraceKey& key : fresh_keys) {
      if (key.robot_id == carrier) {
        carried.unstored.insert(key);
      } else {
        carried.mutation.put_pending.push_back(*FindTrace(key));
      }
    }
    if (full.empty()) {
      // PrepareUpload's count and memory disagree; store the upload alone.
      status = engine->store_->Apply(id, carried.mutation);
      if (!status.ok()) {
        Reload().IgnoreError();
        return status;
      }
    }
  }
  for (size_t i = 0; i < full.size(); ++i) {
    status = ConsolidateRobot(full[i], notices,
                              !stored && i == 0 ? &carried : nullptr,
                              i == 0 ? plan : nullptr);
    if (!status.ok()) return status;
    ++result->consolidations;
  }
  return absl::OkStatus();
}

core::ConsolidationPlan MemoryEngine::Fleet::Plan(
    const std::vector<core::MemoryTrace>& batch) const {
  if (batch.empty()) return {};
  std::mt19937_64 segment_rng(
      SegmentSeed(seed, batch.front().robot_id, batch.front().seq));
  // The engine's options, not memory's: PlanAhead runs without the lock
  // that guards memory (the two hold the same options).
  return core::PlanConsolidation(engine->MemoryOptionsFor(id), batch,
                                 segment_rng);
}

std::optional<core::ConsolidationPlan> MemoryEngine::Fleet::PlanAhead(
    std::span<const core::MemoryTrace> traces) {
  if (traces.empty()) return std::nullopt;
  const std::string& robot_id = traces.front().robot_id;
  for (const core::MemoryTrace& trace : traces) {
    if (trace.robot_id != robot_id) return std::nullopt;
  }
  std::vector<core::MemoryTrace> segment;
  core::SeqSet received;
  {
    absl::ReaderMutexLock lock(&mu);
    if (!stale.ok() || !exists()) return std::nullopt;
    // Planning runs before PrepareUpload's checks: a refused upload (a code
    // of another dimension would overrun the plan's matrix) plans nothing.
    if (!ValidateUpload(id, traces, &meta,
                        engine->options_.max_traces_per_upload)
             .ok()) {
      return std::nullopt;
    }
    auto known = robots.find(robot_id);
    if (known != robots.end()) received = known->second.received;
    auto held = pending.find(robot_id);
    const size_t before = held == pending.end() ? 0 : held->second.size();
    if (before + traces.size() < engine->options_.segment_size) {
      return std::nullopt;
    }
    if (held != pending.end()) segment = held->second;
  }
  // As PrepareUpload accepts them (duplicates, also within the upload, out).
  for (const core::MemoryTrace& trace : traces) {
    if (received.Insert(trace.seq)) segment.push_back(trace);
  }
  if (segment.size() < engine->options_.segment_size) return std::nullopt;
  return Plan(segment);
}

absl::Status MemoryEngine::Fleet::ConsolidateRobot(
    const std::string& robot_id, Notices* notices, CarriedUpload* carried,
    const core::ConsolidationPlan* plan) {
  auto found = pending.find(robot_id);
  if (found == pending.end() || found->second.empty()) return absl::OkStatus();
  const absl::Time start = absl::Now();
  std::vector<core::MemoryTrace> batch = std::move(found->second);
  pending.erase(found);
  for (const core::MemoryTrace& trace : batch) {
    pending_position.erase(trace.key());
    auto domain = pending_by_domain.find(trace.domain);
    if (domain != pending_by_domain.end() && --domain->second == 0) {
      pending_by_domain.erase(domain);
    }
  }

  FleetMutation mutation;
  if (carried != nullptr) mutation = std::move(carried->mutation);
  mutation.erase_pending.reserve(batch.size());
  for (const core::MemoryTrace& trace : batch) {
    if (carried != nullptr && carried->unstored.contains(trace.key())) {
      continue;
    }
    mutation.erase_pending.push_back(trace.key());
  }
  const size_t batch_size = batch.size();
  const uint64_t first_cluster_id = meta.next_cluster_id;
  bool fits = plan != nullptr && plan->keys.size() == batch.size();
  for (size_t i = 0; fits && i < batch.size(); ++i) {
    fits = plan->keys[i] == batch[i].key();
  }
  std::optional<core::ConsolidationPlan> own;
  if (!fits) own = Plan(batch);
  core::ConsolidationResult outcome = memory.Consolidate(
      std::move(batch), first_cluster_id, fits ? *plan : *own);
  ++snapshot_changes;  // forgetting's centroids

  FleetMeta new_meta = meta;
  new_meta.next_cluster_id = first_cluster_id + outcome.added.size();
  absl::flat_hash_set<uint64_t> added_ids;
  for (const core::Cluster& cluster : outcome.added) {
    added_ids.insert(cluster.id);
    new_meta.next_cluster_id =
        std::max(new_meta.next_cluster_id, cluster.id + 1);
  }
  // Clusters no longer held: forgotten whole, or merged into another.
  absl::flat_hash_set<uint64_t> removed_ids;
  for (const core::Cluster& cluster : outcome.forgotten) {
    removed_ids.insert(cluster.id);
  }
  for (const core::ClusterMerge& merge : outcome.merged) {
    removed_ids.insert(merge.from.id);
  }
  // Erasures come first in the store: a merged cluster's moved traces are
  // written again with their survivor.
  for (uint64_t removed : removed_ids) {
    if (!added_ids.contains(removed))
      mutation.erase_clusters.push_back(removed);
  }
  std::sort(mutation.erase_clusters.begin(), mutation.erase_clusters.end());
  // Held clusters that are new or that a merge changed, with every code
  // (a survivor's older traces may have theirs in the index only).
  std::vector<uint64_t> put_ids;
  for (const core::Cluster& cluster : outcome.added) {
    if (!removed_ids.contains(cluster.id)) put_ids.push_back(cluster.id);
  }
  for (uint64_t changed : outcome.changed) {
    if (!added_ids.contains(changed)) put_ids.push_back(changed);
  }
  std::vector<core::TraceKey> kept;
  for (uint64_t put : put_ids) {
    std::optional<core::Cluster> held = memory.WithCentroid(put);
    if (!held.has_value()) continue;
    for (const core::MemoryTrace& trace : held->traces) {
      kept.push_back(trace.key());
    }
    if (absl::Status filled = FillCodes(held->traces); !filled.ok()) {
      FLEETMEM_LOG(kError) << "fleet \"" << id << "\": " << filled;
      Reload().IgnoreError();
      return filled;
    }
    mutation.put_clusters.push_back(*std::move(held));
  }

  const int64_t now_ns = engine->options_.now_ns();
  auto append_event = [&](core::MemoryEvent event) {
    event.id = new_meta.next_event_id++;
    event.timestamp_ns = now_ns;
    mutation.append_events.push_back(std::move(event));
  };
  for (const core::Cluster& cluster : outcome.added) {
    append_event(
        core::DescribeCluster(cluster, core::EventType::kClusterAdded));
  }
  for (const core::Cluster& cluster : outcome.forgotten) {
    append_event(
        core::DescribeCluster(cluster, core::EventType::kClusterForgotten));
  }
  size_t merge_dropped = 0;
  for (const core::ClusterMerge& merge : outcome.merged) {
    core::MemoryEvent event =
        core::DescribeCluster(merge.from, core::EventType::kClusterMerged);
    event.merged_into = merge.into;
    event.traces_dropped = static_cast<uint32_t>(merge.dropped.size());
    append_event(std::move(event));
    merge_dropped += merge.dropped.size();
  }
  new_meta.consolidations += 1;
  new_meta.clusters_forgotten +=
      outcome.forgotten.size() + outcome.merged.size();
  const size_t retained = engine->options_.max_events_per_fleet;
  if (retained > 0 &&
      new_meta.next_event_id - new_meta.first_event_id > retained) {
    new_meta.first_event_id = new_meta.next_event_id - retained;
    mutation.erase_events_before = new_meta.first_event_id;
  }
  mutation.put_meta = true;
  mutation.meta = new_meta;

  // The new clusters' traces came from the batch and still hold their codes
  // (their release comes below).
  absl::Status status = engine->store_->Apply(id, mutation);
  if (!status.ok()) {
    // The static memory already ran ahead of the store: drop it.
    FLEETMEM_LOG(kError) << "fleet \"" << id << "\": consolidation of robot \""
                         << robot_id << "\""
                         << (carried != nullptr
                                 ? " and the upload that filled its segment"
                                 : "")
                         << " not stored: " << status;
    Reload().IgnoreError();
    return status;
  }
  meta = new_meta;
  if (!mutation.append_events.empty()) {
    notices->last_event_id = mutation.append_events.back().id;
  }

  // The batch was indexed while pending and its codes do not change: only
  // what downsampling dropped, what forgetting removed (including clusters
  // of this batch) and what merges dropped leave the index.
  std::vector<core::TraceKey> removed;
  for (const core::MemoryTrace& trace : outcome.downsampled) {
    removed.push_back(trace.key());
  }
  for (const core::Cluster& cluster : outcome.forgotten) {
    for (const core::MemoryTrace& trace : cluster.traces) {
      removed.push_back(trace.key());
    }
  }
  for (const core::ClusterMerge& merge : outcome.merged) {
    for (const core::MemoryTrace& trace : merge.dropped) {
      removed.push_back(trace.key());
    }
  }
  status = UnindexTraces(removed);
  if (!status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\": index update failed, rebuilding: " << status;
    absl::Status reloaded = Reload();
    if (!reloaded.ok()) return reloaded;
  } else {
    ReleaseCodes(kept);
  }

  ConsolidateResult batch_result;
  batch_result.consolidated_traces = batch_size;
  batch_result.downsampled_traces = outcome.downsampled.size() + merge_dropped;
  batch_result.clusters_added = outcome.added.size();
  batch_result.clusters_forgotten =
      outcome.forgotten.size() + outcome.merged.size();
  Accumulate(batch_result, &notices->consolidated);
  ++notices->consolidations;
  notices->consolidation_seconds += absl::ToDoubleSeconds(absl::Now() - start);
  return absl::OkStatus();
}

absl::StatusOr<std::vector<core::MemoryTrace>> MemoryEngine::Fleet::DrawSample(
    std::string_view robot_id, size_t count, std::string_view request_id,
    uint64_t log_position, FleetMutation* mutation) {
  RobotRecord record;
  auto known = robots.find(robot_id);
  if (known != robots.end()) {
    record = known->second;
  } else {
    record.robot_id = std::string(robot_id);
  }
  if (!request_id.empty() && request_id == record.last_sample_request_id) {
    // A retry: the same traces again, as they are now, counted once.
    std::vector<core::MemoryTrace> again;
    for (const core::TraceKey& key : record.last_sample) {
      const core::MemoryTrace* trace = FindTrace(key);
      if (trace != nullptr && trace->cluster_id != 0) again.push_back(*trace);
    }
    absl::Status status = FillCodes(again);
    if (!status.ok()) return status;
    return again;
  }
  std::vector<core::MemoryTrace> traces;
  if (log_position == 0) {
    traces = memory.SampleForReplay(count, rng);
  } else {
    // The same draw on every replica that applies the log entry.
    // The same draw on every replica that applies the log entry, whatever
    // order its sampler's slots are in (a restored or restarted replica's
    // differs from one that applied the log all along).
    std::mt19937_64 logged_rng(SegmentSeed(seed, "log", log_position));
    traces = memory.SampleForReplayInMemoryOrder(count, logged_rng);
  }
  if (traces.empty()) return traces;
  if (absl::Status status = FillCodes(traces); !status.ok()) {
    Reload().IgnoreError();  // drops the incremented counts
    return status;
  }
  record.replayed += traces.size();
  if (!request_id.empty()) {
    record.last_sample_request_id = std::string(request_id);
    record.last_sample.clear();
    for (const core::MemoryTrace& trace : traces) {
      record.last_sample.push_back(trace.key());
    }
  }
  mutation->update_traces = traces;
  mutation->put_robots.push_back(std::move(record));
  if (log_position > meta.log_position) {
    mutation->put_meta = true;
    mutation->meta = meta;
    mutation->meta.log_position = log_position;
  }
  return traces;
}

void MemoryEngine::Fleet::FinishSample(FleetMutation mutation) {
  if (mutation.put_meta) meta = std::move(mutation.meta);
  for (RobotRecord& record : mutation.put_robots) {
    std::string robot_id = record.robot_id;
    robots[robot_id] = std::move(record);
  }
}

FleetStats MemoryEngine::Fleet::Stats() const {
  FleetStats stats;
  stats.traces = memory.trace_count();
  stats.clusters = memory.clusters().size();
  stats.code_dimension = meta.code_dimension;
  stats.encoder_version = meta.encoder_version;
  stats.last_event_id = meta.next_event_id - 1;
  stats.consolidations = meta.consolidations;
  stats.clusters_forgotten = meta.clusters_forgotten;
  stats.first_event_id = std::max<uint64_t>(1, meta.first_event_id);
  stats.quota_rejections = engine->quota_->Rejections(id);
  stats.unindexed_codes = index != nullptr ? index->unindexed() : 0;
  stats.max_clusters = static_cast<uint32_t>(memory.options().max_clusters);
  stats.max_traces_per_cluster =
      static_cast<uint32_t>(memory.options().max_traces_per_cluster);

  std::map<std::string, RobotStats> by_robot;
  std::map<std::string, DomainStats> by_domain;
  auto robot_stats = [&](const std::string& robot_id) -> RobotStats& {
    RobotStats& robot = by_robot[robot_id];
    robot.robot_id = robot_id;
    return robot;
  };
  auto domain_stats = [&](const std::string& domain) -> DomainStats& {
    DomainStats& entry = by_domain[domain];
    entry.domain = domain;
    return entry;
  };
  for (const auto& [robot_id, record] : robots) {
    RobotStats& robot = robot_stats(robot_id);
    robot.max_seq = record.received.max();
    robot.received = record.received.size();
    robot.replayed = record.replayed;
  }
  // O(robots + domains): the counts are kept up to date by every change.
  for (const auto& [robot_id, count] : memory.traces_by_robot()) {
    robot_stats(robot_id).traces = count;
  }
  for (const auto& [domain, count] : memory.traces_by_domain()) {
    domain_stats(domain).traces = count;
  }
  for (const auto& [robot_id, traces] : pending) {
    stats.pending_traces += traces.size();
    robot_stats(robot_id).pending_traces += traces.size();
  }
  for (const auto& [domain, count] : pending_by_domain) {
    domain_stats(domain).pending_traces = count;
  }
  for (auto& [robot_id, robot] : by_robot) {
    stats.robots.push_back(std::move(robot));
  }
  for (auto& [domain, entry] : by_domain) {
    stats.domains.push_back(std::move(entry));
  }
  return stats;
}

MemoryEngine::MemoryEngine(EngineOptions options, MemoryStore* store,
                           PlaceIndexFactory index_factory, EngineHooks hooks)
    : options_(std::move(options)),
      store_(store),
      index_factory_(std::move(index_factory)),
      hooks_(std::move(hooks)) {
  if (!options_.now_ns) {
    options_.now_ns = [] { return absl::GetCurrentTimeNanos(); };
  }
  if (!options_.now_seconds) {
    options_.now_seconds = [] {
      return std::chrono::duration<double>(
                 std::chrono::steady_clock::now().time_since_epoch())
          .count();
    };
  }
  quota_ = std::make_unique<UploadQuota>(options_.limits, options_.now_seconds);
}

MemoryEngine::~MemoryEngine() = default;

absl::StatusOr<std::unique_ptr<MemoryEngine>> MemoryEngine::Open(
    EngineOptions options, MemoryStore* store, PlaceIndexFactory index_factory,
    EngineHooks hooks) {
  absl::Status status = ValidateEngineOptions(options);
  if (!status.ok()) return status;
  if (store == nullptr) {
    return absl::InvalidArgumentError("MemoryEngine::Open needs a store");
  }
  if (!index_factory) {
    return absl::InvalidArgumentError(
        "MemoryEngine::Open needs an index factory");
  }
  std::unique_ptr<MemoryEngine> engine(new MemoryEngine(
      std::move(options), store, std::move(index_factory), std::move(hooks)));
  absl::StatusOr<std::vector<std::string>> fleet_ids = store->ListFleets();
  if (!fleet_ids.ok()) return fleet_ids.status();
  absl::MutexLock fleets_lock(&engine->fleets_mu_);
  for (const std::string& fleet_id : *fleet_ids) {
    auto fleet = std::make_unique<Fleet>(fleet_id, engine.get());
    {
      absl::MutexLock writer(&fleet->writer_mu);
      absl::MutexLock lock(&fleet->mu);
      status = fleet->Reload();
    }
    if (!status.ok()) {
      return absl::Status(
          status.code(),
          absl::StrCat("loading fleet \"", fleet_id, "\": ", status.message()));
    }
    engine->fleets_[fleet_id] = std::move(fleet);
  }
  FLEETMEM_LOG(kInfo) << "memory engine opened with " << fleet_ids->size()
                      << " fleet(s)";
  return engine;
}

size_t MemoryEngine::ReleaseIndexedCodes() {
  std::vector<Fleet*> fleets;
  {
    absl::ReaderMutexLock lock(&fleets_mu_);
    for (const auto& [fleet_id, fleet] : fleets_) fleets.push_back(fleet.get());
  }
  size_t released = 0;
  for (Fleet* fleet : fleets) {
    absl::MutexLock lock(&fleet->mu);
    released += fleet->ReleaseAllCodes();
  }
  return released;
}

absl::Status MemoryEngine::SaveIndexSnapshots(
    const IndexSnapshotSelection& which) {
  std::vector<Fleet*> fleets;
  {
    absl::ReaderMutexLock lock(&fleets_mu_);
    for (const auto& [fleet_id, fleet] : fleets_) fleets.push_back(fleet.get());
  }
  absl::Status first;
  for (Fleet* fleet : fleets) {
    // One snapshot of a fleet at a time (they share the store's file).
    absl::MutexLock one_at_a_time(&fleet->snapshot_mu);
    // writer_mu keeps every change out while the snapshot is written;
    // queries go on beside the shared lock (no writer waits for `mu`
    // without holding writer_mu first). Both are released once the store
    // holds the bytes, before it syncs them.
    fleet->writer_mu.Lock();
    fleet->mu.ReaderLock();
    bool locked = true;
    absl::Time released;
    auto release = [&]() ABSL_NO_THREAD_SAFETY_ANALYSIS {
      if (!locked) return;
      locked = false;
      fleet->mu.ReaderUnlock();
      fleet->writer_mu.Unlock();
      released = absl::Now();
    };
    absl::Cleanup release_on_exit = [&] { release(); };  // every way out
    // A fleet without traces loads fast and would never take its file.
    if (!fleet->stale.ok() || !fleet->exists() || fleet->index == nullptr ||
        fleet->handles.empty() || fleet->handles.size() < which.min_codes ||
        (which.only_changed &&
         fleet->snapshot_saved_at == fleet->snapshot_changes)) {
      continue;
    }
    const uint64_t changes = fleet->snapshot_changes;
    const size_t codes = fleet->handles.size();
    const absl::Time start = absl::Now();
    absl::Status status = fleet->SaveIndexSnapshot(release);
    release();  // the store did not call it (an error, or nothing to sync)
    if (absl::IsUnimplemented(status)) continue;  // this kind of index
    if (!status.ok()) {
      FLEETMEM_LOG(kWarning)
          << "fleet \"" << fleet->id << "\": no index snapshot: " << status;
      first.Update(status);
      continue;
    }
    {
      absl::MutexLock writer(&fleet->writer_mu);
      absl::MutexLock lock(&fleet->mu);
      fleet->snapshot_saved_at = changes;
    }
    const double held = absl::ToDoubleSeconds(released - start);
    FLEETMEM_LOG(kInfo) << "fleet \"" << fleet->id << "\": index snapshot of "
                        << codes << " codes saved in "
                        << absl::ToDoubleSeconds(absl::Now() - start)
                        << " s (uploads waited " << held << " s)";
    if (hooks_.on_index_snapshot) hooks_.on_index_snapshot(fleet->id, held);
  }
  return first;
}

MemoryEngine::Fleet* MemoryEngine::Fleet::Find(const MemoryEngine& engine,
                                               std::string_view fleet_id) {
  absl::ReaderMutexLock lock(&engine.fleets_mu_);
  auto it = engine.fleets_.find(std::string(fleet_id));
  return it == engine.fleets_.end() ? nullptr : it->second.get();
}

absl::StatusOr<MemoryEngine::Fleet*> MemoryEngine::Fleet::FindOrAdd(
    MemoryEngine& engine, std::string_view fleet_id) {
  absl::MutexLock lock(&engine.fleets_mu_);
  auto it = engine.fleets_.find(std::string(fleet_id));
  if (it != engine.fleets_.end()) return it->second.get();
  absl::Status admitted =
      engine.quota_->AdmitNewFleet(fleet_id, engine.fleets_.size());
  if (!admitted.ok()) return admitted;
  auto& fleet = engine.fleets_[std::string(fleet_id)];
  fleet = std::make_unique<Fleet>(std::string(fleet_id), &engine);
  return fleet.get();
}

void MemoryEngine::Fleet::Notify(MemoryEngine& engine,
                                 std::string_view fleet_id,
                                 uint64_t last_event_id) {
  if (last_event_id == 0) return;
  absl::ReaderMutexLock lock(&engine.listeners_mu_);
  for (const auto& [handle, listener] : engine.listeners_) {
    if (listener.fleet_id == fleet_id) listener.callback(last_event_id);
  }
}

absl::StatusOr<UploadResult> MemoryEngine::Upload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) {
    // Validated before a fleet object exists, so a bad first upload leaves
    // nothing behind.
    status = ValidateUpload(fleet_id, traces, nullptr,
                            options_.max_traces_per_upload);
    if (!status.ok()) return status;
    if (traces.empty()) return UploadResult{};
    status = quota_->AdmitDimension(fleet_id, traces[0].code.size());
    if (!status.ok()) return status;
    absl::StatusOr<Fleet*> added = Fleet::FindOrAdd(*this, fleet_id);
    if (!added.ok()) return added.status();
    fleet = *added;
  }
  // Outside the writer lock, so that robots' segments cluster in parallel.
  const std::optional<core::ConsolidationPlan> plan = fleet->PlanAhead(traces);
  UploadResult result;
  Notices notices;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    {
      absl::MutexLock lock(&fleet->mu);
      status = fleet->EnsureLoaded();
    }
    Fleet::PreparedUpload prepared;
    if (status.ok()) {
      absl::ReaderMutexLock lock(&fleet->mu);
      status = fleet->PrepareUpload(traces, log_position, &result, &prepared);
      if (status.ok() && !prepared.mutation.put_pending.empty() &&
          !prepared.fills_segment) {
        status = store_->Apply(fleet->id, prepared.mutation);
        prepared.stored = true;
      }
    }
    absl::MutexLock lock(&fleet->mu);
    if (status.ok() && !prepared.mutation.put_pending.empty()) {
      status = fleet->CommitUpload(std::move(prepared), &result, &notices,
                                   plan ? &*plan : nullptr);
    }
    fleet->PublishHeld();
    notices.consolidated.clusters = fleet->memory.clusters().size();
    notices.consolidated.traces = fleet->memory.trace_count();
    fleet->PublishHeld();
  }
  Fleet::Notify(*this, fleet_id, notices.last_event_id);
  if (notices.consolidations > 0 && hooks_.on_consolidate) {
    hooks_.on_consolidate(fleet_id, notices.consolidated,
                          notices.consolidation_seconds);
  }
  if (!status.ok()) return status;
  if (hooks_.on_upload) hooks_.on_upload(fleet_id, result);
  return result;
}

absl::Status MemoryEngine::CheckUpload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    const FleetShape* shape) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet != nullptr) {
    absl::MutexLock lock(&fleet->mu);
    status = fleet->EnsureLoaded();
    if (!status.ok()) return status;
    if (fleet->exists()) {
      return ValidateUpload(fleet_id, traces, &fleet->meta,
                            options_.max_traces_per_upload);
    }
  }
  if (shape != nullptr) {
    FleetMeta meta;
    meta.code_dimension = shape->code_dimension;
    meta.encoder_version = shape->encoder_version;
    return ValidateUpload(fleet_id, traces, &meta,
                          options_.max_traces_per_upload);
  }
  return ValidateUpload(fleet_id, traces, nullptr,
                        options_.max_traces_per_upload);
}

absl::StatusOr<FleetImage> MemoryEngine::ExportFleet(std::string_view fleet_id,
                                                     uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  absl::MutexLock writer(&fleet->writer_mu);
  {
    absl::MutexLock lock(&fleet->mu);
    status = fleet->EnsureLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    if (log_position > fleet->meta.log_position) {
      FleetMutation mutation;
      mutation.put_meta = true;
      mutation.meta = fleet->meta;
      mutation.meta.log_position = log_position;
      status = store_->Apply(fleet->id, mutation);
      if (!status.ok()) return status;
      fleet->meta.log_position = log_position;
    }
  }
  // The writer lock keeps every change out; readers go on.
  FleetImage image;
  absl::StatusOr<FleetRecord> record = store_->LoadFleet(fleet_id);
  if (!record.ok()) return record.status();
  image.record = *std::move(record);
  constexpr size_t kEventsPerRead = 10000;
  uint64_t after = 0;
  while (true) {
    absl::StatusOr<std::vector<core::MemoryEvent>> events =
        store_->ReadEvents(fleet_id, after, kEventsPerRead);
    if (!events.ok()) return events.status();
    if (events->empty()) break;
    after = events->back().id;
    const bool last = events->size() < kEventsPerRead;
    image.events.insert(image.events.end(),
                        std::make_move_iterator(events->begin()),
                        std::make_move_iterator(events->end()));
    if (last) break;
  }
  return image;
}

absl::Status MemoryEngine::RestoreFleet(std::string_view fleet_id,
                                        FleetImage image) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  if (image.record.fleet_id != fleet_id) {
    return absl::InvalidArgumentError(
        absl::StrCat("an image of fleet \"", image.record.fleet_id,
                     "\" cannot restore fleet \"", V(fleet_id), "\""));
  }
  if (image.record.meta.code_dimension == 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("the image of fleet \"", V(fleet_id),
                     "\" holds no upload (no code dimension)"));
  }
  absl::StatusOr<Fleet*> found = Fleet::FindOrAdd(*this, fleet_id);
  if (!found.ok()) return found.status();
  Fleet* fleet = *found;
  uint64_t last_event_id = 0;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    // What the store holds is erased, whatever memory holds.
    absl::StatusOr<FleetRecord> stored = store_->LoadFleet(fleet_id);
    if (!stored.ok()) return stored.status();
    FleetMutation mutation;
    for (const core::MemoryTrace& trace : stored->pending) {
      mutation.erase_pending.push_back(trace.key());
    }
    for (const core::Cluster& cluster : stored->clusters) {
      mutation.erase_clusters.push_back(cluster.id);
    }
    // Events are put over the stored ones of the same ids (a replica's
    // state is a prefix of the image's). Erasure applies after the puts:
    // only the events the image's retention dropped.
    if (image.record.meta.first_event_id > 1) {
      mutation.erase_events_before = image.record.meta.first_event_id;
    }
    mutation.put_meta = true;
    mutation.meta = image.record.meta;
    mutation.put_pending = std::move(image.record.pending);
    mutation.put_clusters = std::move(image.record.clusters);
    mutation.put_robots = std::move(image.record.robots);
    mutation.append_events = std::move(image.events);
    last_event_id = mutation.meta.next_event_id - 1;
    absl::MutexLock lock(&fleet->mu);
    status = store_->Apply(fleet->id, mutation);
    if (!status.ok()) return status;
    status = fleet->Reload();
  }
  if (status.ok()) Fleet::Notify(*this, fleet_id, last_event_id);
  return status;
}

absl::StatusOr<ConsolidateResult> MemoryEngine::Consolidate(
    std::string_view fleet_id) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  const absl::Time start = absl::Now();
  Notices notices;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    absl::MutexLock lock(&fleet->mu);
    status = fleet->EnsureLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    std::vector<std::string> robot_ids;
    for (const auto& [robot_id, traces] : fleet->pending) {
      if (!traces.empty()) robot_ids.push_back(robot_id);
    }
    for (const std::string& robot_id : robot_ids) {
      status = fleet->ConsolidateRobot(robot_id, &notices);
      if (!status.ok()) break;
    }
    notices.consolidated.clusters = fleet->memory.clusters().size();
    notices.consolidated.traces = fleet->memory.trace_count();
    fleet->PublishHeld();
  }
  Fleet::Notify(*this, fleet_id, notices.last_event_id);
  if (!status.ok()) return status;
  if (hooks_.on_consolidate) {
    hooks_.on_consolidate(fleet_id, notices.consolidated,
                          absl::ToDoubleSeconds(absl::Now() - start));
  }
  return notices.consolidated;
}

absl::StatusOr<std::vector<core::MemoryTrace>> MemoryEngine::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, size_t count,
    std::string_view request_id, uint64_t log_position) {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (status.ok()) status = core::ValidateId("robot_id", robot_id);
  if (status.ok() && !request_id.empty()) {
    status = core::ValidateId("request_id", request_id);
    if (status.ok() && request_id.size() > 64) {
      status =
          absl::InvalidArgumentError("request_id: longer than 64 characters");
    }
  }
  if (!status.ok()) return status;
  if (count < 1 || count > options_.max_sample_count) {
    return absl::InvalidArgumentError(absl::StrCat(
        "count is ", count, " but must be in 1..", options_.max_sample_count));
  }
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);
  absl::StatusOr<std::vector<core::MemoryTrace>> traces;
  {
    absl::MutexLock writer(&fleet->writer_mu);
    FleetMutation mutation;
    {
      absl::MutexLock lock(&fleet->mu);
      status = fleet->EnsureLoaded();
      if (!status.ok()) return status;
      if (!fleet->exists()) return FleetNotFound(fleet_id);
      traces = fleet->DrawSample(robot_id, count, request_id, log_position,
                                 &mutation);
    }
    if (traces.ok() && !mutation.put_robots.empty()) {
      // Readers may see the incremented counts while they are stored; if
      // the store fails, the fleet is reloaded and the call fails.
      {
        absl::ReaderMutexLock lock(&fleet->mu);
        status = store_->Apply(fleet->id, mutation);
      }
      absl::MutexLock lock(&fleet->mu);
      if (status.ok()) {
        fleet->FinishSample(std::move(mutation));
      } else {
        fleet->Reload().IgnoreError();
        traces = status;
      }
    }
  }
  if (traces.ok() && hooks_.on_sample) {
    hooks_.on_sample(fleet_id, traces->size());
  }
  return traces;
}

absl::StatusOr<std::vector<PlaceMatch>> MemoryEngine::QueryPlace(
    std::string_view fleet_id, const PlaceQuery& query) const {
  const absl::Time start = absl::Now();
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (status.ok()) status = core::ValidateCode("code", query.code);
  if (!status.ok()) return status;
  if (query.k > options_.max_query_k) {
    return absl::InvalidArgumentError(absl::StrCat(
        "k is ", query.k, " but must be at most ", options_.max_query_k));
  }
  if (!std::isfinite(query.radius_m)) {
    return absl::InvalidArgumentError("radius_m must be finite");
  }
  const bool use_prior = query.radius_m > 0.0;
  if (use_prior && !IsFinitePlace(query.near)) {
    return absl::InvalidArgumentError("near must have finite coordinates");
  }
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return FleetNotFound(fleet_id);

  std::vector<PlaceMatch> matches;
  {
    absl::ReaderMutexLock lock(&fleet->mu);
    status = fleet->CheckLoaded();
    if (!status.ok()) return status;
    if (!fleet->exists()) return FleetNotFound(fleet_id);
    if (query.code.size() != fleet->meta.code_dimension) {
      return absl::InvalidArgumentError(absl::StrCat(
          "code has dimension ", query.code.size(), " but fleet \"",
          V(fleet_id), "\" uses ", fleet->meta.code_dimension));
    }
    if (fleet->index == nullptr) {
      return absl::InternalError(
          absl::StrCat("fleet \"", V(fleet_id), "\" has no index"));
    }
    SearchParams params;
    params.k = std::max<size_t>(query.k, 1);
    params.unit_query = true;  // as the codes were added (AddNormalized)
    if (use_prior) {
      params.accept = [fleet, &query](uint64_t handle) {
        const std::optional<core::TraceKey> key = fleet->handles.Key(handle);
        if (!key.has_value()) return false;
        const core::MemoryTrace* trace = fleet->FindTrace(*key);
        return trace != nullptr &&
               PlaceDistance(trace->place, query.near) <= query.radius_m;
      };
    }
    absl::StatusOr<std::vector<Neighbor>> neighbors =
        fleet->index->Search(query.code, params);
    if (!neighbors.ok()) return neighbors.status();
    matches.reserve(neighbors->size());
    for (const Neighbor& neighbor : *neighbors) {
      const std::optional<core::TraceKey> key = fleet->handles.Key(neighbor.id);
      if (!key.has_value()) continue;
      const core::MemoryTrace* trace = fleet->FindTrace(*key);
      if (trace == nullptr) continue;
      absl::StatusOr<core::MemoryTrace> copy = fleet->WithCode(*trace);
      if (!copy.ok()) return copy.status();
      matches.push_back(PlaceMatch{*std::move(copy), neighbor.distance});
    }
  }
  if (hooks_.on_query) {
    hooks_.on_query(fleet_id, absl::ToDoubleSeconds(absl::Now() - start));
  }
  return matches;
}

absl::StatusOr<FleetStats> MemoryEngine::GetStats(
    std::string_view fleet_id) const {
  return Fleet::ReadExisting(
      *this, fleet_id, [](const Fleet& fleet) -> absl::StatusOr<FleetStats> {
        return fleet.Stats();
      });
}

absl::StatusOr<uint64_t> MemoryEngine::LogPosition(
    std::string_view fleet_id) const {
  absl::StatusOr<uint64_t> position = Fleet::ReadExisting(
      *this, fleet_id, [](const Fleet& fleet) -> absl::StatusOr<uint64_t> {
        return fleet.meta.log_position;
      });
  if (absl::IsNotFound(position.status())) return 0;
  return position;
}

absl::Status CheckTraces(std::string_view fleet_id,
                         std::span<const core::MemoryTrace> traces,
                         const FleetShape* shape, size_t max_traces) {
  if (shape == nullptr) {
    return ValidateUpload(fleet_id, traces, nullptr, max_traces);
  }
  FleetMeta meta;
  meta.code_dimension = shape->code_dimension;
  meta.encoder_version = shape->encoder_version;
  return ValidateUpload(fleet_id, traces, &meta, max_traces);
}

std::optional<FleetShape> MemoryEngine::Shape(std::string_view fleet_id) const {
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return std::nullopt;
  absl::ReaderMutexLock lock(&fleet->mu);
  if (!fleet->exists()) return std::nullopt;
  return FleetShape{fleet->meta.code_dimension, fleet->meta.encoder_version};
}

uint64_t MemoryEngine::HeldTraces(std::string_view fleet_id) const {
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  return fleet == nullptr ? 0 : fleet->held.load(std::memory_order_relaxed);
}

core::SeqSet MemoryEngine::Received(std::string_view fleet_id,
                                    std::string_view robot_id) const {
  const Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return {};
  absl::ReaderMutexLock lock(&fleet->mu);
  auto it = fleet->robots.find(robot_id);
  return it == fleet->robots.end() ? core::SeqSet() : it->second.received;
}

absl::Status MemoryEngine::CheckFleetExists(std::string_view fleet_id) const {
  return Fleet::ReadExisting(
             *this, fleet_id,
             [](const Fleet&) -> absl::StatusOr<bool> { return true; })
      .status();
}

absl::StatusOr<std::vector<core::MemoryEvent>> MemoryEngine::ReadEvents(
    std::string_view fleet_id, uint64_t after_event) const {
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (!status.ok()) return status;
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return std::vector<core::MemoryEvent>();
  // Under the reader lock: retention erases events only under the writer
  // lock, so none can vanish between the check and the read.
  absl::ReaderMutexLock lock(&fleet->mu);
  const uint64_t first = std::max<uint64_t>(1, fleet->meta.first_event_id);
  if (after_event > 0 && after_event + 1 < first) {
    return absl::OutOfRangeError(absl::StrCat(
        "events ", after_event + 1, "..", first - 1, " of fleet \"",
        V(fleet_id), "\" were erased by the retention bound (",
        options_.max_events_per_fleet,
        " events, max_events_per_fleet); the oldest kept is ", first,
        ": re-read the fleet's state (GetStats, queries) and watch again from "
        "after_event 0"));
  }
  return store_->ReadEvents(fleet_id, after_event,
                            options_.max_events_per_read);
}

uint64_t MemoryEngine::Subscribe(std::string_view fleet_id,
                                 EventListener listener) {
  absl::MutexLock lock(&listeners_mu_);
  const uint64_t handle = next_listener_++;
  listeners_[handle] = Listener{std::string(fleet_id), std::move(listener)};
  return handle;
}

void MemoryEngine::Unsubscribe(uint64_t handle) {
  absl::MutexLock lock(&listeners_mu_);
  listeners_.erase(handle);
}

std::vector<std::string> MemoryEngine::ListFleets() const {
  std::vector<const Fleet*> fleets;
  {
    absl::ReaderMutexLock lock(&fleets_mu_);
    for (const auto& [fleet_id, fleet] : fleets_) fleets.push_back(fleet.get());
  }
  std::vector<std::string> fleet_ids;
  for (const Fleet* fleet : fleets) {
    absl::ReaderMutexLock lock(&fleet->mu);
    if (fleet->exists()) fleet_ids.push_back(fleet->id);
  }
  std::sort(fleet_ids.begin(), fleet_ids.end());
  return fleet_ids;
}

namespace {

TracePlace PlaceOf(const core::MemoryTrace& trace) {
  return TracePlace{trace.robot_id, trace.seq, trace.domain, trace.place,
                    trace.reward};
}

ClusterSummary Summarize(const core::Cluster& cluster, bool include_places) {
  const core::MemoryEvent described =
      core::DescribeCluster(cluster, core::EventType::kClusterAdded);
  ClusterSummary summary;
  summary.cluster_id = cluster.id;
  summary.robot_id = cluster.robot_id;
  summary.trace_count = described.trace_count;
  summary.centroid_place = described.centroid_place;
  summary.mean_reward = described.mean_reward;
  for (const core::MemoryTrace& trace : cluster.traces) {
    ++summary.robots[trace.robot_id];
    ++summary.domains[trace.domain];
    if (include_places) summary.places.push_back(PlaceOf(trace));
  }
  return summary;
}

}  // namespace

absl::StatusOr<ClusterListing> MemoryEngine::ListClusters(
    std::string_view fleet_id, bool include_places) const {
  return Fleet::ReadExisting(
      *this, fleet_id,
      [include_places](const Fleet& fleet) -> absl::StatusOr<ClusterListing> {
        ClusterListing listing;
        listing.clusters.reserve(fleet.memory.clusters().size());
        for (const auto& [cluster_id, cluster] : fleet.memory.clusters()) {
          listing.clusters.push_back(Summarize(cluster, include_places));
        }
        if (!include_places) return listing;
        for (const auto& [robot_id, traces] : fleet.pending) {
          for (const core::MemoryTrace& trace : traces) {
            listing.pending.push_back(PlaceOf(trace));
          }
        }
        return listing;
      });
}

absl::StatusOr<TracePage> MemoryEngine::ListTraces(
    std::string_view fleet_id, const std::optional<core::TraceKey>& after,
    size_t page_size) const {
  if (page_size == 0) {
    return absl::InvalidArgumentError("page_size: must be at least 1");
  }
  return Fleet::ReadExisting(
      *this, fleet_id, [&](const Fleet& fleet) -> absl::StatusOr<TracePage> {
        // Every trace after the cursor; then the page's first ones by key.
        std::vector<const core::MemoryTrace*> candidates;
        TracePage page;
        auto consider = [&](const std::vector<core::MemoryTrace>& traces) {
          page.total += traces.size();
          for (const core::MemoryTrace& trace : traces) {
            if (!after.has_value() || *after < trace.key()) {
              candidates.push_back(&trace);
            }
          }
        };
        for (const auto& [cluster_id, cluster] : fleet.memory.clusters()) {
          consider(cluster.traces);
        }
        for (const auto& [robot_id, traces] : fleet.pending) consider(traces);
        const size_t taken = std::min(page_size, candidates.size());
        std::partial_sort(
            candidates.begin(), candidates.begin() + taken, candidates.end(),
            [](const core::MemoryTrace* a, const core::MemoryTrace* b) {
              return std::tie(a->robot_id, a->seq) <
                     std::tie(b->robot_id, b->seq);
            });
        page.traces.reserve(taken);
        for (size_t i = 0; i < taken; ++i) {
          absl::StatusOr<core::MemoryTrace> copy =
              fleet.WithCode(*candidates[i]);
          if (!copy.ok()) return copy.status();
          page.traces.push_back(*std::move(copy));
        }
        page.more = candidates.size() > taken;
        return page;
      });
}

absl::Status MemoryEngine::Checkpoint(const std::string& directory) {
  return store_->Checkpoint(directory);
}

}  // namespace fleetmem::engine
