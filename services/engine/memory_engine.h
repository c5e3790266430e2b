// The fleet memory service without a transport: one StaticMemory per fleet
// kept in step with durable storage and a place index, automatic
// consolidation per robot segment, replay sampling, queries and events.
//
// Thread-safe: calls on different fleets run in parallel; on one fleet,
// mutations run one at a time, and queries and stats share a reader lock
// with each other and with the store writes of uploads and samples: a query
// waits while a mutation changes memory (an upload's commit, a replay draw)
// and during a consolidation (k-means and its store write), not for an
// upload's or a sample's fsync.
// Every mutation is durable in the store before the call returns OK (the
// apply of a log entry: written to the store's write-ahead log, synced
// later, since the log is the durable copy: FleetMutation::sync); if the
// store fails, the fleet is reloaded from the store and the error returned.
// Uploaded traces and consolidations become visible only once durable; a
// sample's incremented replay counts are visible while they are being
// stored, and a store failure reverts them (by the reload).
// Each static-memory code is held once: by the place index where it keeps
// codes as given (PlaceIndex::HoldsCode), memory's copy freed; every trace
// the engine returns or stores carries its code.
#ifndef FLEETMEM_SERVICES_ENGINE_MEMORY_ENGINE_H_
#define FLEETMEM_SERVICES_ENGINE_MEMORY_ENGINE_H_

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "services/core/memory_options.h"
#include "services/core/trace_filter.h"
#include "services/core/types.h"
#include "services/engine/fleet_log.h"
#include "services/engine/fleet_settings.h"
#include "services/engine/memory_store.h"
#include "services/engine/place_index.h"
#include "services/engine/upload_quota.h"

namespace fleetmem::engine {

struct EngineOptions {
  // Memory parameters of every fleet (K, N_max, K_max, gamma, ...).
  core::MemoryOptions memory;
  // Per-fleet replacements of `memory`, by fleet id (e.g. an ablation fleet
  // with clustering off next to the production fleets).
  std::map<std::string, core::MemoryOptions, std::less<>> fleet_memory;
  // A robot's pending traces are consolidated automatically once this many
  // have accumulated.
  size_t segment_size = 200;
  // Most traces one upload message may carry.
  size_t max_traces_per_upload = 1000;
  // Most traces one SampleReplay may ask for.
  size_t max_sample_count = 10000;
  // Most traces one UpdateRewards or GetTraces may name.
  size_t max_keys_per_call = 10000;
  // A SampleReplay applied from a log entry is drawn from a generator
  // seeded by the entry's sequence. With this set (distributed mode) it is
  // drawn in memory order (StaticMemory::SampleForReplayInMemoryOrder,
  // O(traces) per draw), so that replicas whose samplers hold their slots
  // in other orders (one restored from a snapshot, one that applied the
  // whole log) draw the same traces; off (embedded mode: one server), the
  // sublinear draw (StaticMemory::SampleForReplay).
  bool draw_in_memory_order = false;
  // The index of a fleet whose settings name its own kind or graph codes
  // (CreateFleet's IndexSettings); empty: every fleet gets the Open's index
  // factory's.
  FleetIndexFactory fleet_index_factory;
  // Most matches one QueryPlace may ask for.
  size_t max_query_k = 1000;
  // Most codes one QueryPlace may carry.
  size_t max_query_codes = 100;
  // Most bytes of traces one read returns, so that no call can make the
  // server hold an unbounded answer (a REST answer's JSON is about 3.5 times
  // this, gRPC's serialised copy once more). A trace counts 4 bytes per code
  // element plus its attachment. A ListTraces page ends early (with a next
  // page); a QueryPlace whose matches hold more is refused; a SampleReplay
  // is refused before its draw when count x (4 x dimension + the largest
  // attachment the fleet holds) is over it (the message names the most that
  // fit).
  size_t max_read_bytes = 32 << 20;
  // Events returned by one ReadEvents call at most.
  size_t max_events_per_read = 1000;
  // Event retention: a fleet keeps its newest this-many events; older ones
  // are erased with the consolidation that makes new ones (0 keeps all). A
  // watcher whose cursor points before the oldest kept event gets
  // OUT_OF_RANGE (ReadEvents).
  size_t max_events_per_fleet = 100'000;
  // Upload quotas (rates, stored traces, fleets, code dimension).
  QuotaOptions limits;
  // Nanoseconds since the epoch, for event timestamps (injected for tests).
  std::function<int64_t()> now_ns;
  // Monotonic seconds for the rate limits (injected for tests).
  std::function<double()> now_seconds;
};

absl::Status ValidateEngineOptions(const EngineOptions& options);

struct UploadResult {
  uint64_t accepted = 0;
  uint64_t duplicates = 0;
  uint64_t consolidations = 0;
};

// What every upload to a fleet must match; fixed by its first upload.
struct FleetShape {
  uint32_t code_dimension = 0;
  std::string encoder_version;
};

// Checks a whole upload as MemoryEngine::Upload does (INVALID_ARGUMENT
// naming the trace and field): at most `max_traces`, each trace valid and of
// the fleet's `shape`; `shape` null for a fleet that does not exist yet (its
// first upload then fixes the shape from traces[0]).
absl::Status CheckTraces(std::string_view fleet_id,
                         std::span<const core::MemoryTrace> traces,
                         const FleetShape* shape, size_t max_traces);

struct ConsolidateResult {
  uint64_t consolidated_traces = 0;
  uint64_t downsampled_traces = 0;
  uint64_t clusters_added = 0;
  uint64_t clusters_forgotten = 0;
  uint64_t clusters = 0;
  uint64_t traces = 0;
};

// What a fleet is (GetFleet): its shape and the settings it runs with.
struct FleetInfo {
  FleetShape shape;
  FleetSettings settings;
  // The settings are the fleet's own (CreateFleet, UpdateFleet); false:
  // the server's configuration, which it follows.
  bool own_settings = false;
};

// What DeleteTraces did.
struct DeleteResult {
  uint64_t deleted = 0;           // traces removed, static memory and pending
  uint64_t pending_deleted = 0;   // of them, those awaiting consolidation
  uint64_t clusters_changed = 0;  // kept traces; centroids recomputed
  uint64_t clusters_removed = 0;  // left empty
  uint64_t traces = 0;            // static + pending traces after it
};

// What UpdateRewards did.
struct RewardsResult {
  // Traces held (static memory or pending) rescored, each once.
  uint64_t updated = 0;
  // The keys named that the fleet does not hold (never uploaded, forgotten,
  // downsampled or deleted), each once, in the order of their last naming.
  std::vector<core::TraceKey> not_held;
};

// What GetTraces found.
struct TraceLookup {
  // The traces held, with their codes, in the order named (each once).
  std::vector<core::MemoryTrace> traces;
  // The keys named that the fleet does not hold, in the order named.
  std::vector<core::TraceKey> missing;
};

struct PlaceQuery {
  std::vector<float> code;
  size_t k = 1;  // 0 means 1
  // Position prior; ignored when radius_m <= 0.
  core::Place near;
  double radius_m = 0.0;
  // Only traces it matches are considered (none set: every trace).
  core::ReadFilter filter;
};

struct PlaceMatch {
  core::MemoryTrace trace;
  float distance = 0.0f;  // between normalised codes
};

struct RobotStats {
  std::string robot_id;
  uint64_t traces = 0;
  uint64_t pending_traces = 0;
  uint64_t max_seq = 0;
  uint64_t received = 0;
  uint64_t replayed = 0;
};

struct DomainStats {
  std::string domain;
  uint64_t traces = 0;
  uint64_t pending_traces = 0;
};

struct FleetStats {
  uint64_t traces = 0;
  uint64_t pending_traces = 0;
  uint64_t clusters = 0;
  uint32_t code_dimension = 0;
  std::string encoder_version;
  uint64_t last_event_id = 0;
  uint64_t consolidations = 0;
  uint64_t clusters_forgotten = 0;
  uint32_t max_clusters = 0;
  uint32_t max_traces_per_cluster = 0;
  // Oldest event still kept (event retention).
  uint64_t first_event_id = 1;
  // Uploads refused by each limit since the server started.
  std::map<std::string, uint64_t> quota_rejections;
  // Codes the place index holds outside its search graph (PlaceIndex::
  // unindexed: the tiered index's backlog).
  uint64_t unindexed_codes = 0;
  std::vector<RobotStats> robots;    // sorted by robot_id
  std::vector<DomainStats> domains;  // sorted by domain
};

// Where one trace was observed, without its code (maps, dashboards).
struct TracePlace {
  std::string robot_id;
  uint64_t seq = 0;
  std::string domain;
  core::Place place;
  float reward = 0.0f;
};

// One cluster of the static memory at a glance.
struct ClusterSummary {
  uint64_t cluster_id = 0;
  std::string robot_id;  // robot whose segment made it
  uint32_t trace_count = 0;
  core::Place centroid_place;  // mean place of its traces
  float mean_reward = 0.0f;
  std::map<std::string, uint32_t> robots;   // traces per robot
  std::map<std::string, uint32_t> domains;  // traces per domain
  std::vector<TracePlace> places;           // with include_places only
};

struct ClusterListing {
  std::vector<ClusterSummary> clusters;  // by id (oldest first)
  std::vector<TracePlace> pending;       // with include_places only
};

struct TracePage {
  std::vector<core::MemoryTrace> traces;  // by (robot_id, seq)
  bool more = false;                      // traces follow the last one
  uint64_t total = 0;                     // static + pending traces now
};

// Which fleets MemoryEngine::SaveIndexSnapshots saves.
struct IndexSnapshotSelection {
  // Only fleets whose place index holds at least this many codes (a small
  // index rebuilds in moments; 0: every fleet with codes).
  size_t min_codes = 0;
  // Only fleets that changed since the store's snapshot last matched them:
  // traces indexed or removed, or clusters consolidated, since it was
  // written or loaded (replay counts are not in a snapshot).
  bool only_changed = false;
  // With only_changed: also fleets whose snapshot no longer describes the
  // store (MemoryStore::IndexSnapshotCurrent: a write since it was saved,
  // such as a replay draw or a reward update, which leave the index as it
  // was), so that the next start takes the clusters from the snapshot's
  // memory image. For a stop: periodic snapshots would write a fleet that
  // draws replays at every turn.
  bool refresh_memory_image = false;
};

// Observers of the engine (metrics); every member may be empty. Called
// outside fleet locks.
struct EngineHooks {
  std::function<void(std::string_view fleet, const UploadResult&)> on_upload;
  // `consolidations` robot batches (as GetStats' `consolidations` counts
  // them; 0 for a Consolidate call that found nothing pending), their
  // summed result and the time they took.
  std::function<void(std::string_view fleet, size_t consolidations,
                     const ConsolidateResult&, double seconds)>
      on_consolidate;
  std::function<void(std::string_view fleet, size_t count)> on_sample;
  // Retention deleted `traces` of the fleet.
  std::function<void(std::string_view fleet, uint64_t traces)> on_retention;
  std::function<void(std::string_view fleet, double seconds)> on_query;
  // An index snapshot of the fleet was saved; its mutating calls waited
  // `paused_seconds` for it (the write, not the sync that follows).
  std::function<void(std::string_view fleet, double paused_seconds)>
      on_index_snapshot;
};

// NOT_FOUND for a fleet that does not exist, as the engine says it.
absl::Status FleetNotFound(std::string_view fleet_id);

class MemoryEngine {
 public:
  // Loads every fleet from `store`. The store must outlive the engine.
  static absl::StatusOr<std::unique_ptr<MemoryEngine>> Open(
      EngineOptions options, MemoryStore* store,
      PlaceIndexFactory index_factory, EngineHooks hooks = {});
  ~MemoryEngine();

  // Validates all of `traces` first (ids, finite values, the fleet's code
  // dimension and encoder version, at most max_traces_per_upload); any error
  // is INVALID_ARGUMENT and changes nothing. Then the quotas (limits): a
  // refusal is RESOURCE_EXHAUSTED naming the limit and changes nothing. Then
  // stores the traces whose
  // (robot_id, seq) is new as pending (durably), counts the rest as
  // duplicates, and consolidates each robot whose pending traces reached
  // segment_size. The first upload to an unknown fleet creates it with the
  // dimension and encoder version of its traces.
  //
  // `log_position`: the sequence of the fleet's log entry this upload is
  // (WritePath's local log, or distributed mode's replicated log); stored in
  // the same write as the traces it adds (LogPosition), unless it adds none.
  // An entry of a log meets no limit (rates, stored traces, fleets, code
  // dimension: it was admitted by them before it was acknowledged,
  // engine/admission.h, and must apply even past a limit lowered since):
  // only a direct call (0) passes the limits here; and its
  // traces were checked whole where it was appended, so its apply checks
  // their shape (count, dimension, encoder version) and not every value
  // again: a batch is validated once.
  absl::StatusOr<UploadResult> Upload(std::string_view fleet_id,
                                      std::span<const core::MemoryTrace> traces,
                                      uint64_t log_position = 0);

  // The last log entry stored with an upload's traces (0 for an unknown
  // fleet, or none): the fleet's log is applied through it (WritePath's
  // local log in embedded mode, the replicated log in distributed mode).
  absl::StatusOr<uint64_t> LogPosition(std::string_view fleet_id) const;

  // For a write path that admits uploads before they are applied (WritePath):
  // cheap views of a fleet that wait for no consolidation, except Received
  // and Shape, which wait for the fleet's reader lock.
  // The fleet's shape, or nullopt if it does not exist yet.
  std::optional<FleetShape> Shape(std::string_view fleet_id) const;
  // Traces the fleet holds (static memory and pending), as of its last
  // change; 0 for an unknown fleet.
  uint64_t HeldTraces(std::string_view fleet_id) const;
  // Every seq the fleet has received from `robot_id` (empty if none).
  core::SeqSet Received(std::string_view fleet_id,
                        std::string_view robot_id) const;
  // The quotas every upload passes (rates, stored traces, fleets, dimension).
  UploadQuota& quota() { return *quota_; }
  const EngineOptions& options() const { return options_; }

  // Distributed mode's snapshots (services/cluster): the fleet's whole
  // stored state, events included, read while none of its writes runs.
  // `log_position`, if greater than the fleet's, is recorded first (in the
  // store and in the image) as the last log entry applied: the caller has
  // applied every entry through it. NOT_FOUND for an unknown fleet.
  absl::StatusOr<FleetImage> ExportFleet(std::string_view fleet_id,
                                         uint64_t log_position = 0);
  // A deleted fleet's image (DeleteFleet applied, nothing uploaded since)
  // is its kept position and ids, no traces.
  //
  // Replaces whatever this engine holds of the fleet with `image` (one
  // atomic store write: its stored records are erased, the image's put)
  // and reloads it; a fleet it does not hold is added. A deleted fleet's
  // image leaves the fleet deleted at its position, as DeleteFleet does.
  // INVALID_ARGUMENT, with nothing changed, for an image of another fleet
  // or of a fleet without its first upload that is not a deleted one; the
  // store's error, with nothing changed, if the write fails.
  absl::Status RestoreFleet(std::string_view fleet_id, FleetImage image);

  // Consolidates every robot's pending traces (one batch per robot).
  // NOT_FOUND for an unknown fleet.
  absl::StatusOr<ConsolidateResult> Consolidate(std::string_view fleet_id);

  // Eq. 18 refresh for `robot_id`: 1 <= count <= max_sample_count.
  // `request_id` (optional, 1-64 characters of [A-Za-z0-9._:-]) makes a
  // retry safe: when it equals the robot's previous request id, the traces
  // of that call are returned again (as they are now; forgotten ones are
  // left out) and no replay count changes. The id and the traces drawn are
  // stored atomically with the counts they incremented.
  //
  // `log_position`: the sequence of the fleet's log entry this call is
  // (both modes log it: engine/log_applier.h). The draw is then seeded
  // from the fleet's seed and the position, not from the fleet's running
  // generator, so every replica applying the entry draws the same traces;
  // the position is stored with the counts.
  //
  // `filter` (optional): only the traces it matches are drawn, with their
  // weights; the draw then reads every trace held, in memory order
  // (StaticMemory::SampleForReplayInMemoryOrder).
  absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, size_t count,
      std::string_view request_id = {}, uint64_t log_position = 0,
      const core::ReadFilter* filter = nullptr);
  // SampleReplay's checks of its arguments alone (ids, count, the filter if
  // any), which need no fleet: what a writer checks before it logs the call.
  absl::Status CheckSampleReplay(
      std::string_view fleet_id, std::string_view robot_id, size_t count,
      std::string_view request_id,
      const core::ReadFilter* filter = nullptr) const;

  // Nearest traces to query.code among the static memory's and the pending
  // ones (cluster_id 0), nearest first.
  // Makes the fleet with `record`'s shape and settings, stored as its own
  // (a CreateFleet; its log's first entry). FAILED_PRECONDITION if it
  // exists; CheckCreateFleet's refusals. `log_position` as DeleteTraces'.
  absl::Status CreateFleet(std::string_view fleet_id,
                           const CreateFleetRecord& record,
                           uint64_t log_position = 0);
  // INVALID_ARGUMENT naming the field: a dimension outside 1..65,536 or
  // over the server's max_code_dimension, an encoder version or place unit
  // too long, settings out of range (core::ValidateMemoryOptions),
  // negative retention.
  absl::Status CheckCreateFleet(std::string_view fleet_id,
                                const CreateFleetRecord& record) const;
  // Changes the fleet's settings (stored as its own from then on): the
  // next consolidation uses the new K, N_max, K_max and forgetting rule (a
  // smaller K_max or N_max applies then), the next draw the new gamma.
  // Returns the settings after it. INVALID_ARGUMENT if the result is out
  // of range (nothing changed).
  absl::StatusOr<FleetSettings> UpdateFleet(std::string_view fleet_id,
                                            const FleetSettingsUpdate& update,
                                            uint64_t log_position = 0);
  // The fleet's shape and settings; NOT_FOUND if it does not exist.
  absl::StatusOr<FleetInfo> GetFleet(std::string_view fleet_id) const;

  // Removes the fleet: everything stored for it goes in one atomic store
  // write (MemoryStore::DeleteFleet), then its memory and index; the
  // traces it held (static and pending). Afterwards the fleet does not
  // exist (NOT_FOUND) until CreateFleet or an upload makes it again, anew
  // (its settings the server's, its robots' seqs forgotten); its event ids
  // go on from where they were, so a watch's cursor never meets an old id
  // again. `log_position` as for DeleteTraces (the delete's entry is kept
  // as the fleet's position).
  absl::StatusOr<uint64_t> DeleteFleet(std::string_view fleet_id,
                                       uint64_t log_position = 0);

  // Removes every trace of the fleet that `filter` matches, from the
  // static memory and the pending traces, in one atomic store write:
  // clusters that keep some traces get their centroids recomputed
  // (StaticMemory::Remove), empty ones leave; one kTracesDeleted event per
  // cluster touched (and one for the pending traces). The robots' received
  // seqs stay: a deleted trace uploaded again is a duplicate, not stored.
  // `filter` must pass ValidateTraceFilter and set some criterion
  // (INVALID_ARGUMENT: a filter that selects every trace). A non-zero
  // `log_position` is the log entry's: an entry at or below the fleet's
  // position was applied already and changes nothing.
  absl::StatusOr<DeleteResult> DeleteTraces(std::string_view fleet_id,
                                            const core::TraceFilter& filter,
                                            uint64_t log_position = 0);
  // Retention (FleetSettings::max_age_seconds, max_traces_per_robot) as
  // of `now_ns`: a DeleteTraces of the fleet's traces observed before
  // now - max_age and of each robot's oldest beyond its newest
  // max_traces_per_robot (by seq), with its events. Nothing for a fleet
  // without retention.
  absl::StatusOr<DeleteResult> EnforceRetention(std::string_view fleet_id,
                                                int64_t now_ns,
                                                uint64_t log_position = 0);
  // Checks DeleteTraces' arguments as it does, without the fleet.
  static absl::Status CheckDeleteTraces(std::string_view fleet_id,
                                        const core::TraceFilter& filter);
  // Sets R_ex, R_in and R of the held traces named (static memory: their
  // replay weights follow, Eq. 18; pending: their downsampling by reward
  // at consolidation), in one atomic store write. Keys not held are listed,
  // not refused. `log_position` as for DeleteTraces.
  absl::StatusOr<RewardsResult> UpdateRewards(
      std::string_view fleet_id, std::span<const core::RewardUpdate> updates,
      uint64_t log_position = 0);
  // INVALID_ARGUMENT naming the update: more than max_keys_per_call, a
  // malformed robot id, a reward not finite or R_ex + R_in < 0.
  absl::Status CheckUpdateRewards(
      std::string_view fleet_id,
      std::span<const core::RewardUpdate> updates) const;
  // The held traces with `keys` (static memory or pending), with their
  // codes. INVALID_ARGUMENT for more than max_keys_per_call keys, a
  // malformed key, or traces over max_read_bytes.
  absl::StatusOr<TraceLookup> GetTraces(
      std::string_view fleet_id, std::span<const core::TraceKey> keys) const;

  absl::StatusOr<std::vector<PlaceMatch>> QueryPlace(
      std::string_view fleet_id, const PlaceQuery& query) const;
  // QueryPlace of `query`'s code and of each of `more_codes` (a robot's
  // last frames, a sequence search), with `query`'s k and prior, under one
  // read of the fleet: one answer per code, in order. At most
  // max_query_codes codes in all; their answers share one max_read_bytes.
  absl::StatusOr<std::vector<std::vector<PlaceMatch>>> QueryPlaces(
      std::string_view fleet_id, const PlaceQuery& query,
      std::span<const std::vector<float>> more_codes) const;

  // NOT_FOUND for an unknown fleet.
  absl::StatusOr<FleetStats> GetStats(std::string_view fleet_id) const;

  // Bulk loading (ImportTraces, docs/api.md). Until `until`, the fleet's
  // place index leaves the codes it gets outside its graph (an exact scan
  // finds them meanwhile, GetStats counts them as unindexed_codes): no
  // linking in the background nor as an upload's back-pressure, so that
  // IndexDeferred builds the graph once from all of them. A later call
  // moves the time; one already past ends the deferral (the background
  // linking resumes by itself then, too). It holds for an index the fleet
  // is given later (a reload) and is not kept across a restart.
  // NOT_FOUND for a fleet this engine does not hold (yet).
  absl::Status DeferIndexing(std::string_view fleet_id, absl::Time until);
  // True while a deferral of the fleet is in force.
  bool IndexingDeferred(std::string_view fleet_id) const;
  // Ends the fleet's deferral and links every code waiting into its graph
  // now, on the index's insert threads (the caller's among them), in large
  // steps with queries let in between; returns once none waits. The
  // index's error stops it (the codes left stay found by the exact scan).
  // NOT_FOUND for an unknown fleet.
  absl::Status IndexDeferred(std::string_view fleet_id);

  // OK if the fleet exists (its first upload is durable); INVALID_ARGUMENT
  // for a malformed id, NOT_FOUND otherwise. Cheap: no stats are computed.
  absl::Status CheckFleetExists(std::string_view fleet_id) const;

  // Up to max_events_per_read events with id > after_event (any valid fleet
  // id; an unknown fleet has none yet). OUT_OF_RANGE if after_event > 0 and
  // events after it were already erased by the retention bound (the message
  // names the oldest kept event; resume after_event = 0 to start from it).
  absl::StatusOr<std::vector<core::MemoryEvent>> ReadEvents(
      std::string_view fleet_id, uint64_t after_event) const;

  // Calls `listener` (outside locks, on the mutating thread) after new events
  // of `fleet_id` are durable, with the id of the newest. Returns a handle
  // for Unsubscribe. Listeners must be quick and must not call Unsubscribe.
  using EventListener = std::function<void(uint64_t last_event_id)>;
  uint64_t Subscribe(std::string_view fleet_id, EventListener listener);
  void Unsubscribe(uint64_t handle);

  std::vector<std::string> ListFleets() const;

  // The static memory's clusters; with `include_places` also every trace's
  // place (and the pending traces'). NOT_FOUND for an unknown fleet.
  absl::StatusOr<ClusterListing> ListClusters(std::string_view fleet_id,
                                              bool include_places) const;

  // Up to `page_size` (>= 1) traces of the static memory and the pending
  // ones, with codes, whose key is after `after` (all when nullopt), by
  // (robot_id, seq); fewer (at least one) where more would be over
  // max_read_bytes. NOT_FOUND for an unknown fleet.
  absl::StatusOr<TracePage> ListTraces(
      std::string_view fleet_id, const std::optional<core::TraceKey>& after,
      size_t page_size) const;

  // The store's Checkpoint: a consistent copy of every fleet in the new
  // directory `directory`, with every write acknowledged before the call.
  // Serving goes on meanwhile.
  absl::Status Checkpoint(const std::string& directory);

  // Saves each fleet's place index, trace handles and forgetting's centroid
  // bookkeeping through the store (MemoryStore::SaveIndexSnapshot), so that
  // the next Open loads them instead of rebuilding the index: at 1,000,000
  // traces the HNSW graph takes minutes to rebuild (docs/performance.md).
  // A fleet's mutating calls wait while its snapshot is written (seconds at
  // 1,000,000 256-d traces; the store's sync of the file follows without
  // the wait); its queries do not. Open reconciles a
  // snapshot with the store, so one taken while serving (periodically, the
  // server's `index_snapshot_interval_seconds`) shortens the rebuild after a
  // crash to the traces stored since; one taken at a clean shutdown, once
  // no call runs any more, leaves nothing to rebuild. Fleets whose index
  // cannot be saved (FLANN) are skipped. Returns the first error (the other
  // fleets are still saved); a fleet with an error keeps its earlier
  // snapshot, if any.
  absl::Status SaveIndexSnapshots(const IndexSnapshotSelection& which = {});

  // One copy of each code: frees the engine's copies of static-memory codes
  // that the place index keeps itself (PlaceIndex::HoldsCode: the exact,
  // HNSW and tiered indexes do from Add on; FLANN never does). Each
  // consolidation does this for its new clusters and each load for every
  // trace, so fleetmem's indexes need no more; an index that takes codes
  // over only later would need this called now and then. O(traces) under
  // each fleet's exclusive lock. Returns the number of codes freed.
  size_t ReleaseIndexedCodes();

  // The memory parameters in force for `fleet_id`.
  const core::MemoryOptions& MemoryOptionsFor(std::string_view fleet_id) const;

 private:
  struct Fleet;
  // Which traces a delete removes (`leaves`), and the selection named in
  // the pending traces' event.
  struct Selection {
    std::function<bool(const core::MemoryTrace&)> leaves;
    core::TraceFilter filter;
  };
  // DeleteTraces and EnforceRetention: the traces `select` picks from the
  // fleet (under its lock), removed in one store write.
  absl::StatusOr<DeleteResult> Delete(
      std::string_view fleet_id, uint64_t log_position,
      const std::function<Selection(const Fleet&)>& select);
  // RestoreFleet of a deleted fleet's image: the fleet deleted at
  // kept.log_position, with kept's ids.
  absl::Status RestoreDeletedFleet(Fleet& fleet, const FleetMeta& kept);
  MemoryEngine(EngineOptions options, MemoryStore* store,
               PlaceIndexFactory index_factory, EngineHooks hooks);

  EngineOptions options_;
  MemoryStore* store_;
  PlaceIndexFactory index_factory_;
  // An empty index for a fleet with these index settings: the fleet's own
  // kind or codes (options_.fleet_index_factory) or the server's.
  std::unique_ptr<PlaceIndex> NewIndex(size_t dimension,
                                       const IndexSettings& index) const;
  EngineHooks hooks_;
  std::unique_ptr<UploadQuota> quota_;

  mutable absl::Mutex fleets_mu_;
  absl::flat_hash_map<std::string, std::unique_ptr<Fleet>> fleets_
      ABSL_GUARDED_BY(fleets_mu_);

  absl::Mutex listeners_mu_;
  struct Listener {
    std::string fleet_id;
    EventListener callback;
  };
  absl::flat_hash_map<uint64_t, Listener> listeners_
      ABSL_GUARDED_BY(listeners_mu_);
  uint64_t next_listener_ ABSL_GUARDED_BY(listeners_mu_) = 1;
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_MEMORY_ENGINE_H_
