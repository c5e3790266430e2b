#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <functional>
#include <map>
#include <optional>
#include <random>
#include <span>
#include <string>
#include <system_error>
#include <thread>
#include <tuple>
#include <utility>

#include "services/engine/memory_engine.h"

#if __has_include(<malloc.h>)
#include <malloc.h>
#endif

#include "absl/cleanup/cleanup.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/feature_space.h"
#include "services/core/static_memory.h"
#include "services/core/validation.h"
#include "services/engine/memory_engine_fleet.h"
#include "services/engine/memory_image.h"
#include "services/engine/trace_handles.h"

namespace fleetmem::engine {

void ReturnFreedMemory() {
#if defined(__GLIBC__)
  malloc_trim(0);
#endif
}

namespace {

// Version of the engine's part of an index snapshot: ENG2 records the
// fleet's index settings (its kind, HNSW's M and ef) after the dimension,
// so that a fleet with its own index loads its snapshot into one of that
// kind; ENG1 (before) is read as the server's kind. ENG3 (2026-12-01)
// adds the memory image (its length, then memory_image.h) before the
// handles, and the handles' length before them, so that the loading
// thread can parse both while the snapshot's thread loads the index.
constexpr uint32_t kIndexSnapshotFormatV1 = 0x454e4731;  // "ENG1"
constexpr uint32_t kIndexSnapshotFormatV2 = 0x454e4732;  // "ENG2"
constexpr uint32_t kIndexSnapshotFormat = 0x454e4733;    // "ENG3"

// A one-time signal between two threads, as absl::Notification, on a
// Mutex and a CondVar: `make test-tsan` annotates those for Debian's
// uninstrumented absl (tools/tsan/absl_mutex_annotations.cc) but not the
// Condition wait inside Notification, so ThreadSanitizer saw no order
// between a notify and what the other thread read after its wait.
class Signal {
 public:
  void Notify() {
    absl::MutexLock lock(&mu_);
    notified_ = true;
    cv_.SignalAll();
  }
  void Wait() {
    absl::MutexLock lock(&mu_);
    while (!notified_) cv_.Wait(&mu_);
  }
  bool notified() {
    absl::MutexLock lock(&mu_);
    return notified_;
  }

 private:
  absl::Mutex mu_;
  absl::CondVar cv_;
  bool notified_ ABSL_GUARDED_BY(mu_) = false;
};

// How ReadSnapshot's thread and the loading thread share a snapshot.
struct SnapshotHandOff {
  // Set before the read: a snapshot with a memory image hands the image and
  // the handles' bytes to the loading thread (ReadWithImage), which parses
  // both while this thread checks the snapshot's checksum and then loads
  // the index; the file stays mapped until the loading thread notifies
  // `released` (SnapshotReader::Release: after memory's restore, which
  // reads forgetting's centroids from the file).
  bool split = false;
  // Notified once `loaded.image` and `loaded.handle_bytes` are set
  // (image_loaded) or it is known that they will not be.
  Signal image_read;
  // Notified once the checksum's verdict is in `checked`, or it is known
  // that there will be none (`checked` is then not OK). What the loading
  // thread parsed from the image is used only once `checked` is OK.
  Signal check_done;
  absl::Status checked =
      absl::DataLossError("the snapshot's checksum was not checked");
  // Notified once the snapshot's handles are in `loaded` (handles_loaded)
  // or it is known that they will not be; `loaded.handles` is not touched
  // after that.
  Signal handles_read;
  // Notified once `loaded.centroids` are read (centroids_read) or it is
  // known that they will not be: memory restores beside the index's load.
  Signal centroids_read;
  Signal released;
  // Whether forgetting's centroids are borrowed from the mapped file
  // (LoadedSnapshot::centroid_bytes) or copied: borrowed while the loading
  // thread holds the file (split, before `mapping_released`); a release
  // before memory's restore copies what was borrowed.
  absl::Mutex centroids_mu;
  bool mapping_released ABSL_GUARDED_BY(centroids_mu) = false;
  bool centroids_borrowed ABSL_GUARDED_BY(centroids_mu) = false;
};

// Reads the handles (the next handle, then TraceHandles) from `in` into
// `loaded`.
absl::Status LoadHandles(core::ByteReader& in, LoadedSnapshot& loaded) {
  if (!in.Get(&loaded.next_handle)) return absl::DataLossError("bad header");
  absl::Status status = loaded.handles.Load(in, loaded.next_handle);
  loaded.handles_loaded = status.ok();
  return status;
}

// The same from exactly `bytes`.
absl::Status LoadHandles(std::span<const char> bytes, LoadedSnapshot& loaded) {
  core::ByteReader in(bytes);
  absl::Status status = LoadHandles(in, loaded);
  if (status.ok() && in.remaining() != 0) {
    loaded.handles_loaded = false;
    status = absl::DataLossError("bytes after the handles");
  }
  return status;
}

// Runs `first` on this thread and `second` on a thread of its own (one
// after the other if no thread can be started): memory's restore in two
// halves (core::RunBoth), for the core the index's load beside it leaves
// free once it ends (at 1,000,000 traces it ends first; at 10,000,000 it
// does not).
void RunOnTwoThreads(const std::function<void()>& first,
                     const std::function<void()>& second) {
  std::thread thread;
  try {
    thread = std::thread(second);
  } catch (const std::system_error&) {
    first();
    second();
    return;
  }
  absl::Cleanup join = [&thread] { thread.join(); };
  first();
}

// ENG3's memory image and handles, as spans into the snapshot.
absl::Status TakeImageAndHandles(core::ByteReader& in,
                                 std::span<const char>* image,
                                 std::span<const char>* handle_bytes) {
  uint64_t image_size = 0;
  uint64_t handles_size = 0;
  if (!in.Get(&image_size) || !in.GetSpan(image_size, image) ||
      !in.Get(&handles_size) || !in.GetSpan(handles_size, handle_bytes)) {
    return absl::DataLossError("truncated memory image or handles");
  }
  return absl::OkStatus();
}

// Reads a snapshot's header: its format, the codes' dimension and (from
// ENG2) the index settings.
absl::Status ReadHeader(core::ByteReader& in, uint32_t* format,
                        uint32_t* dimension, IndexSettings* index) {
  if (!in.Get(format) ||
      (*format != kIndexSnapshotFormat && *format != kIndexSnapshotFormatV2 &&
       *format != kIndexSnapshotFormatV1) ||
      !in.Get(dimension) || *dimension == 0) {
    return absl::DataLossError("bad header");
  }
  if (*format == kIndexSnapshotFormatV1) return absl::OkStatus();
  int32_t kind = 0;
  if (!in.Get(&kind) || !in.Get(&index->hnsw_m) ||
      !in.Get(&index->hnsw_ef_search) || kind < 0 ||
      kind > static_cast<int32_t>(IndexSettings::Kind::kAuto)) {
    return absl::DataLossError("bad index settings");
  }
  index->kind = static_cast<IndexSettings::Kind>(kind);
  return absl::OkStatus();
}

// The handles and centroids of a snapshot whose checksum passed, then its
// index (made by `factory`): ReadSnapshot's part after the check.
absl::Status LoadCheckedSnapshot(core::ByteReader& in, uint32_t format,
                                 const IndexSettings& index,
                                 std::span<const char> handle_bytes,
                                 bool handed, const FleetIndexFactory& factory,
                                 LoadedSnapshot& loaded,
                                 SnapshotHandOff& hand_off, absl::Time start) {
  if (!handed) {
    hand_off.image_read.Notify();
    absl::Status handles = format == kIndexSnapshotFormat
                               ? LoadHandles(handle_bytes, loaded)
                               : LoadHandles(in, loaded);
    if (!handles.ok()) return handles;
    loaded.handles_seconds = absl::ToDoubleSeconds(absl::Now() - start);
    hand_off.handles_read.Notify();
  }
  uint64_t centroid_size = 0;
  std::span<const char> centroid_bytes;
  if (!in.Get(&centroid_size) || !in.GetSpan(centroid_size, &centroid_bytes)) {
    return absl::DataLossError("truncated centroids");
  }
  {
    // 100 MB at 1,000,000 traces (100,060 centroids), 1 GB at 10,000,000:
    // borrowed from the file while the loading thread keeps it mapped.
    absl::MutexLock lock(&hand_off.centroids_mu);
    if (handed && !hand_off.mapping_released) {
      loaded.centroid_bytes = centroid_bytes;
      hand_off.centroids_borrowed = true;
    } else {
      loaded.centroids.assign(centroid_bytes.begin(), centroid_bytes.end());
      loaded.centroid_bytes = loaded.centroids;
    }
  }
  loaded.centroids_read = true;
  hand_off.centroids_read.Notify();
  loaded.index = factory(loaded.dimension, index);
  if (loaded.index == nullptr) return absl::InternalError("no index made");
  const absl::Time index_start = absl::Now();
  absl::Status status = loaded.index->Load(in);
  loaded.index_seconds = absl::ToDoubleSeconds(absl::Now() - index_start);
  loaded.unindexed = loaded.index->unindexed();
  if (status.ok() && in.remaining() != 0) {
    status = absl::DataLossError("bytes after the index");
  }
  loaded.index_status = status;
  return absl::OkStatus();
}

// Reads `fleet_id`'s index snapshot through `store` into `loaded` and loads
// its index (made by `factory` for the snapshot's dimension and index
// settings). Needs nothing of the fleet, so it runs beside the store's
// LoadFleet (each is seconds long at 1,000,000 traces); `hand_off` says
// what it leaves to the loading thread and when: with `split`, the image
// and the handles are handed over before the checksum is checked, and the
// loading thread parses them meanwhile.
void ReadSnapshot(MemoryStore& store, const FleetIndexFactory& factory,
                  std::string_view fleet_id, LoadedSnapshot& loaded,
                  SnapshotHandOff& hand_off) {
  bool handed = false;
  absl::Cleanup notify = [&] {
    // After the read: with the spans handed over, the loading thread has
    // released them (so parsed the handles) before it returned.
    hand_off.image_read.Notify();
    hand_off.check_done.Notify();
    hand_off.handles_read.Notify();
    hand_off.centroids_read.Notify();
  };
  const absl::Time start = absl::Now();
  loaded.status = store.ReadIndexSnapshot(
      fleet_id, [&](const IndexSnapshotBytes& snapshot) -> absl::Status {
        // The loading thread reads the spans until it releases them
        // (SnapshotReader::Release).
        absl::Cleanup keep_mapped = [&] {
          if (handed) hand_off.released.Wait();
        };
        core::ByteReader in(snapshot.bytes, snapshot.file);
        uint32_t format = 0;
        IndexSettings index;
        if (absl::Status header =
                ReadHeader(in, &format, &loaded.dimension, &index);
            !header.ok()) {
          return header;
        }
        std::span<const char> image;
        std::span<const char> handle_bytes;
        if (format == kIndexSnapshotFormat) {
          absl::Status taken = TakeImageAndHandles(in, &image, &handle_bytes);
          if (!taken.ok()) return taken;
          if (hand_off.split) {
            loaded.image = image;
            loaded.handle_bytes = handle_bytes;
            loaded.image_loaded = true;
            handed = true;
            hand_off.image_read.Notify();
          }
        }
        const absl::Time check_start = absl::Now();
        absl::Status checked = snapshot.check();
        loaded.check_seconds = absl::ToDoubleSeconds(absl::Now() - check_start);
        hand_off.checked = checked;
        hand_off.check_done.Notify();
        if (!checked.ok()) return checked;
        return LoadCheckedSnapshot(in, format, index, handle_bytes, handed,
                                   factory, loaded, hand_off, start);
      });
}

// How Reload's read of the store went beside the snapshot's thread.
struct ReadTimes {
  absl::Duration waited_for_handles;  // by the store's read
  // The clusters came from the snapshot's memory image, without their codes
  // (the store read the rest of the fleet).
  bool from_image = false;
  // Waiting for the image, decoding it and the handles, and for the
  // checksum's verdict.
  absl::Duration image;
};

// The fleet's record with its clusters from the memory image the snapshot's
// thread hands over (`hand_off`), and the rest from `store`; the
// snapshot's handles are parsed here too, beside that thread's checksum
// and index. nullopt if the snapshot has no image that decodes or fails
// its checksum (the store's read then reads the clusters).
absl::StatusOr<std::optional<FleetRecord>> ReadWithImage(
    MemoryStore& store, std::string_view fleet_id, LoadedSnapshot& loaded,
    SnapshotHandOff& hand_off) {
  absl::StatusOr<FleetRecord> record = store.LoadFleetWithoutClusters(fleet_id);
  if (!record.ok()) return record.status();
  hand_off.image_read.Wait();
  if (!loaded.image_loaded) return std::nullopt;
  const absl::Time start = absl::Now();
  core::ByteReader in(loaded.image);
  absl::StatusOr<std::vector<core::Cluster>> clusters = LoadMemoryImage(in);
  if (clusters.ok() && in.remaining() != 0) {
    clusters = absl::DataLossError("the memory image has bytes after its end");
  }
  absl::Status handles = LoadHandles(loaded.handle_bytes, loaded);
  loaded.handles_seconds = absl::ToDoubleSeconds(absl::Now() - start);
  loaded.image = {};
  loaded.handle_bytes = {};
  // Parsed before the checksum passed: used only after.
  hand_off.check_done.Wait();
  if (!hand_off.checked.ok() || !handles.ok()) {
    // The snapshot is unusable: the store's read, the index rebuilt.
    loaded.handles = TraceHandles();
    loaded.handles_loaded = false;
    return std::nullopt;
  }
  if (!clusters.ok()) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                           << "\": reading the store's clusters: "
                           << clusters.status();
    return std::nullopt;
  }
  record->clusters = *std::move(clusters);
  return std::optional<FleetRecord>(*std::move(record));
}

// A fleet's index snapshot read on a second thread (ReadSnapshot) beside
// the loading thread's read of the store (Read), into `loaded`; joined by
// Finish (or the destructor). After a read of the clusters from the
// snapshot's memory image the thread is still loading the index when Read
// returns: memory restores meanwhile (LoadedSnapshot::await_centroids,
// await_all).
class SnapshotReader {
 public:
  SnapshotReader(MemoryStore& store, FleetIndexFactory factory,
                 std::string_view fleet_id, LoadedSnapshot& loaded)
      : store_(store),
        factory_(std::move(factory)),
        fleet_id_(fleet_id),
        loaded_(loaded) {}
  ~SnapshotReader() {
    Finish();
    loaded_.await_centroids = nullptr;
    loaded_.await_all = nullptr;
  }

  // Reads `fleet_id` from the store while the second thread reads the
  // snapshot and loads its index there, without the codes the snapshot's
  // handles say it holds but a sample for Reconcile's check. The store
  // asks about each code once it has read the fleet's records (which takes
  // about as long as the snapshot's checksum and handles): the wait is
  // short, and reading every code meanwhile would cost more. When the
  // store says that the snapshot is current, the fleet's clusters come
  // from its memory image instead, and this thread parses the image and
  // the handles while the second checks the checksum and loads the index
  // (ReadWithImage); the thread is then left running (Finish).
  absl::StatusOr<FleetRecord> Read(ReadTimes* times);

  // Releases the file (the centroids dropped: Read released it already
  // unless memory restores from the image, which is over by then), then
  // joins the thread (once; LoadedSnapshot::thread_waited_seconds says how
  // long it waited); the index must then hold what the handles name.
  void Finish();

 private:
  // Lets the thread unmap the snapshot's file (once). The centroids it
  // lent from there (LoadedSnapshot::centroid_bytes) are copied first if
  // `keep_centroids` (memory restores later), else dropped (memory has
  // restored from them, or will not: 100 MB at 1,000,000 traces, whose
  // copy took 1 s on a VM with slow page faults).
  void Release(bool keep_centroids);

  MemoryStore& store_;
  const FleetIndexFactory factory_;
  const std::string_view fleet_id_;
  LoadedSnapshot& loaded_;
  SnapshotHandOff hand_off_;
  std::thread thread_;
  bool finished_ = false;
};

absl::StatusOr<FleetRecord> SnapshotReader::Read(ReadTimes* times) {
  hand_off_.split = store_.IndexSnapshotCurrent(fleet_id_);
  auto read_snapshot = [this] {
    ReadSnapshot(store_, factory_, fleet_id_, loaded_, hand_off_);
  };
  try {
    thread_ = std::thread(read_snapshot);
  } catch (const std::system_error&) {
    hand_off_.split = false;  // nothing to hand to: it ends before
    read_snapshot();          // no thread: one after the other
  }
  bool handles_waited = false;  // asked once per trace: one wait
  auto held_by_snapshot = [&](const core::TraceKey& key) {
    if (!handles_waited) {
      const absl::Time wait = absl::Now();
      hand_off_.handles_read.Wait();
      times->waited_for_handles = absl::Now() - wait;
      handles_waited = true;
    }
    if (!loaded_.handles_loaded) return false;
    const uint64_t handle = loaded_.handles.Find(key);
    return handle != 0 &&
           !FleetIndex::CheckedOnLoad(handle, loaded_.handles.size());
  };
  absl::StatusOr<std::optional<FleetRecord>> imaged = std::nullopt;
  if (hand_off_.split) {
    const absl::Time start = absl::Now();
    imaged = ReadWithImage(store_, fleet_id_, loaded_, hand_off_);
    times->image = absl::Now() - start;
  }
  times->from_image = imaged.ok() && imaged->has_value();
  // Memory restores from the image with the centroids in the file: the
  // file is released after (await_all). Otherwise now: the store's read
  // waits for the handles, which the thread sets once it let the file go.
  if (!times->from_image) Release(/*keep_centroids=*/true);
  absl::StatusOr<FleetRecord> record =
      !imaged.ok() ? imaged.status()
      : times->from_image
          ? **std::move(imaged)
          : store_.LoadFleetWithoutHeldCodes(fleet_id_, held_by_snapshot);
  if (times->from_image) {
    loaded_.await_centroids = [this] { hand_off_.centroids_read.Wait(); };
    loaded_.await_all = [this] { Finish(); };
  } else {
    Finish();
  }
  return record;
}

void SnapshotReader::Release(bool keep_centroids) {
  {
    absl::MutexLock lock(&hand_off_.centroids_mu);
    if (hand_off_.mapping_released) return;
    hand_off_.mapping_released = true;
    if (hand_off_.centroids_borrowed) {
      if (keep_centroids) {
        loaded_.centroids.assign(loaded_.centroid_bytes.begin(),
                                 loaded_.centroid_bytes.end());
        loaded_.centroid_bytes = loaded_.centroids;
      } else {
        loaded_.centroid_bytes = {};
      }
      hand_off_.centroids_borrowed = false;
    }
  }
  hand_off_.released.Notify();
}

void SnapshotReader::Finish() {
  if (finished_) return;
  finished_ = true;
  // After Read's Release of its own in every case but a read of the
  // memory image, whose restore is over.
  Release(/*keep_centroids=*/false);
  const absl::Time start = absl::Now();
  if (thread_.joinable()) thread_.join();
  loaded_.thread_waited_seconds = absl::ToDoubleSeconds(absl::Now() - start);
  // The index must hold what the handles name (the handles may have been
  // parsed on the loading thread).
  if (loaded_.status.ok() && loaded_.index_status.ok() &&
      (!loaded_.handles_loaded ||
       loaded_.index->size() != loaded_.handles.size())) {
    loaded_.index_status =
        absl::DataLossError("the index does not match its handles");
  }
  if (!loaded_.status.ok() || !loaded_.index_status.ok()) {
    loaded_.index.reset();
  }
}

}  // namespace

absl::Status MemoryEngine::Fleet::Reload(bool with_snapshot) {
  const absl::Time start = absl::Now();
  LoadedSnapshot snapshot;
  ReadTimes times;
  // Joined before `snapshot` goes (declared after it).
  SnapshotReader reader(
      *engine->store_,
      [this](size_t dimension, const IndexSettings& index) {
        return engine->NewIndex(dimension, index);
      },
      id, snapshot);
  absl::StatusOr<FleetRecord> record =
      with_snapshot ? reader.Read(&times) : engine->store_->LoadFleet(id);
  // From the image too: the handles parsed there (handles_loaded).
  const bool codes_left_out = snapshot.handles_loaded;
  if (codes_left_out && !times.from_image && record.ok() &&
      (!snapshot.status.ok() || !snapshot.index_status.ok())) {
    // Its index cannot be used (another kind, other settings): the index
    // is rebuilt from the store's codes; memory may still take the
    // snapshot's centroids. (After a read from the memory image the thread
    // is still loading the index: Rebuild finds out, and the codes are
    // read below.)
    record = engine->store_->LoadFleet(id);
  }
  const absl::Time read = absl::Now();
  absl::Status status = !record.ok()    ? record.status()
                        : with_snapshot ? Rebuild(*std::move(record), &snapshot)
                                        : Rebuild(*std::move(record));
  if (!status.ok() && codes_left_out) {
    // The snapshot was not usable after all: the store's codes are needed.
    FLEETMEM_LOG(kWarning) << "fleet \"" << id
                           << "\": loading with its index snapshot failed ("
                           << status << "); reading the codes from the store";
    record = engine->store_->LoadFleet(id);
    status = record.ok() ? Rebuild(*std::move(record)) : record.status();
  }
  if (status.ok() && exists()) {
    if (times.from_image) {
      FLEETMEM_LOG(kInfo) << "fleet \"" << id << "\": " << memory.trace_count()
                          << " traces in " << memory.clusters().size()
                          << " clusters taken from its index snapshot's "
                             "memory image in "
                          << absl::ToDoubleSeconds(times.image)
                          << " s (the store read none of them)";
    }
    FLEETMEM_LOG(kInfo) << "fleet \"" << id
                        << "\" loaded: " << memory.trace_count()
                        << " traces in " << memory.clusters().size()
                        << " clusters, " << pending.size()
                        << " pending; store read "
                        << absl::ToDoubleSeconds(read - start)
                        << " s, memory and index "
                        << absl::ToDoubleSeconds(absl::Now() - read)
                        << " s (the store's read waited "
                        << absl::ToDoubleSeconds(times.waited_for_handles)
                        << " s for the snapshot's handles; its checksum "
                        << snapshot.check_seconds
                        << " s; the load waited for its thread "
                        << snapshot.thread_waited_seconds << " s)";
  }
  if (!status.ok()) {
    FLEETMEM_LOG(kError) << "fleet \"" << id
                         << "\" could not be reloaded: " << status;
    Rebuild(FleetRecord{}).IgnoreError();
    stale = status;
    return status;
  }
  // The load's temporaries (its records, decoded and freed a trace at a
  // time, and the codes the index took) leave holes amid the heap that
  // glibc keeps: 880 MiB of 2,209 resident at 1,000,000 traces when the
  // codes stayed in the store. Once per load.
  if (memory.trace_count() >= 10'000) ReturnFreedMemory();
  stale = absl::OkStatus();
  PublishHeld();
  return absl::OkStatus();
}

absl::Status MemoryEngine::Fleet::EnsureLoaded() {
  if (index.get() != nullptr && index.get()->Damaged()) {
    // A row read from the index snapshot's file failed its check: the
    // index is built again from the store's codes (the file is replaced
    // by the next snapshot).
    FLEETMEM_LOG(kWarning) << "fleet \"" << id
                           << "\": its index met damage in its snapshot's "
                              "file; rebuilding the index from the store";
    return Reload(/*with_snapshot=*/false);
  }
  if (stale.ok()) return absl::OkStatus();
  return Reload();
}

absl::Status MemoryEngine::Fleet::CheckLoaded() const {
  if (stale.ok()) return absl::OkStatus();
  return absl::UnavailableError(
      absl::StrCat("fleet \"", id, "\" is not loaded after a storage error (",
                   stale.message(), "); retry later"));
}

void MemoryEngine::Fleet::Reset(const FleetMeta& stored) {
  meta = stored;
  memory = core::StaticMemory(OptionsOf(stored));
  {
    absl::MutexLock lock(&plan_options_mu);
    plan_options = memory.options();
  }
  pending.Clear();
  largest_attachment = 0;
  robots.clear();
  index.Reset();
}

absl::StatusOr<std::vector<const core::MemoryTrace*>>
MemoryEngine::Fleet::GatherTraces(std::vector<core::Cluster>& clusters) {
  // The traces stay in their clusters' vectors when the clusters move into
  // memory, so the index can read them while memory restores.
  std::vector<const core::MemoryTrace*> traces;
  absl::flat_hash_set<uint64_t> cluster_ids;
  cluster_ids.reserve(clusters.size());
  for (core::Cluster& cluster : clusters) {
    if (!cluster_ids.insert(cluster.id).second) {
      return absl::DataLossError(absl::StrCat("fleet \"", id, "\" has cluster ",
                                              cluster.id, " twice"));
    }
    for (core::MemoryTrace& trace : cluster.traces) {
      trace.cluster_id = cluster.id;
      largest_attachment =
          std::max(largest_attachment, trace.attachment.size());
      traces.push_back(&trace);
    }
  }
  for (const auto& [robot_id, robot_pending] : pending.by_robot()) {
    for (const core::MemoryTrace& trace : robot_pending) {
      traces.push_back(&trace);
    }
  }
  return traces;
}

absl::Status MemoryEngine::Fleet::Rebuild(FleetRecord record,
                                          LoadedSnapshot* snapshot) {
  Reset(record.meta);
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
  // An empty index of the fleet's dimension (also after a snapshot that
  // could not be reconciled left none).
  auto start_index = [&] {
    index.Start(engine->NewIndex(meta.code_dimension, meta.settings
                                                          ? meta.settings->index
                                                          : IndexSettings()));
    if (index.get() != nullptr) return absl::OkStatus();
    return absl::InternalError(
        absl::StrCat("the index factory made no index for fleet \"", id, "\""));
  };
  if (absl::Status started = start_index(); !started.ok()) return started;
  absl::StatusOr<std::vector<const core::MemoryTrace*>> gathered =
      GatherTraces(record.clusters);
  if (!gathered.ok()) return gathered.status();
  const std::vector<const core::MemoryTrace*>& traces = *gathered;
  bool restored = false;
  if (!traces.empty()) {
    const absl::Time start = absl::Now();
    absl::Status status =
        snapshot == nullptr
            ? absl::NotFoundError("no index snapshot read")
            : LoadFromSnapshot(*snapshot, record.clusters, traces, &restored);
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
  if (index.get() == nullptr) {
    if (absl::Status started = start_index(); !started.ok()) return started;
  }
  if (std::any_of(
          traces.begin(), traces.end(),
          [](const core::MemoryTrace* trace) { return trace->code.empty(); })) {
    // Left in the store for a snapshot that could not be used: Reload
    // reads them and rebuilds.
    return absl::DataLossError("codes left out of the load for its snapshot");
  }
  absl::Status status = restored ? index.Add(traces) : index.Add(traces, [&] {
    for (core::Cluster& cluster : record.clusters) {
      memory.Restore(std::move(cluster));
    }
  });
  if (!status.ok()) {
    status = absl::Status(
        status.code(), absl::StrCat("fleet \"", id, "\": ", status.message()));
  }
  if (status.ok()) ReleaseAllCodes();
  return status;
}

size_t MemoryEngine::Fleet::ReleaseCodes(
    const std::vector<core::TraceKey>& keys) {
  if (index.get() == nullptr || keys.empty()) return 0;
  std::vector<const core::TraceKey*> asked;
  asked.reserve(keys.size());
  for (const core::TraceKey& key : keys) asked.push_back(&key);
  const std::vector<bool> held = index.HoldsCodes(asked);
  size_t released = 0;
  for (size_t i = 0; i < keys.size(); ++i) {
    if (held[i] && memory.DropCode(keys[i])) ++released;
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
  return ReleaseCodes(keys);
}

absl::StatusOr<core::MemoryTrace> MemoryEngine::Fleet::WithCode(
    core::MemoryTrace trace) const {
  if (!trace.code.empty()) return trace;
  if (!index.CopyCode(trace.key(), &trace.code)) {
    return absl::InternalError(absl::StrCat(
        "fleet \"", id, "\": the code of trace (\"", trace.robot_id, "\", ",
        trace.seq, ") is neither in memory nor in the index"));
  }
  return trace;
}

absl::Status MemoryEngine::Fleet::FillCodes(
    std::vector<core::MemoryTrace>& traces) const {
  // One turn of the index's lock for all (PlaceIndex::CopyCodes).
  std::vector<core::TraceKey> keys;
  std::vector<std::vector<float>*> codes;
  for (core::MemoryTrace& trace : traces) {
    if (!trace.code.empty()) continue;
    keys.push_back(trace.key());
    codes.push_back(&trace.code);
  }
  if (keys.empty()) return absl::OkStatus();
  std::vector<const core::TraceKey*> asked;
  asked.reserve(keys.size());
  for (const core::TraceKey& key : keys) asked.push_back(&key);
  if (index.CopyCodes(asked, codes)) return absl::OkStatus();
  for (core::MemoryTrace& trace : traces) {  // which one: WithCode says
    if (!trace.code.empty()) continue;
    absl::StatusOr<core::MemoryTrace> filled = WithCode(std::move(trace));
    if (!filled.ok()) return filled.status();
    trace = *std::move(filled);
  }
  return absl::OkStatus();
}

void MemoryEngine::Fleet::AddPending(core::MemoryTrace trace) {
  largest_attachment = std::max(largest_attachment, trace.attachment.size());
  pending.Add(std::move(trace));
}

const core::MemoryTrace* MemoryEngine::Fleet::FindTrace(
    const core::TraceKey& key) const {
  if (const core::MemoryTrace* trace = memory.Find(key)) return trace;
  return pending.Find(key);
}

absl::Status MemoryEngine::Fleet::SaveIndexSnapshot(
    const std::function<void()>& written) const {
  return engine->store_->SaveIndexSnapshot(
      id,
      [this](core::ByteWriter& out) {
        out.Put<uint32_t>(kIndexSnapshotFormat);
        out.Put<uint32_t>(meta.code_dimension);
        const IndexSettings settings =
            meta.settings ? meta.settings->index : IndexSettings();
        out.Put<int32_t>(static_cast<int32_t>(settings.kind));
        out.Put<int32_t>(settings.hnsw_m);
        out.Put<int32_t>(settings.hnsw_ef_search);
        // The memory image (its length first).
        auto centroid_of = [this](uint64_t cluster_id) {
          return memory.CentroidOf(cluster_id);
        };
        SaveMemoryImage(memory.clusters(), centroid_of, out);
        out.Put<uint64_t>(index.SavedHandlesSize());
        index.SaveHandles(out);
        // Forgetting's centroid bookkeeping, length first so that a load
        // can hand it to memory while the index reads what follows.
        core::ByteWriter counter([](std::span<const char>) {});
        memory.SaveCentroids(counter);
        out.Put<uint64_t>(counter.written());
        memory.SaveCentroids(out);
        return index.SaveIndex(out);
      },
      written);
}

absl::Status MemoryEngine::Fleet::LoadFromSnapshot(
    LoadedSnapshot& snapshot, std::vector<core::Cluster>& clusters,
    const std::vector<const core::MemoryTrace*>& traces, bool* restored) {
  // Memory restores while the snapshot's thread may still load the index:
  // it needs the centroids alone.
  if (snapshot.await_centroids) snapshot.await_centroids();
  auto await_all = [&snapshot] {
    if (snapshot.await_all) snapshot.await_all();
  };
  if (!snapshot.centroids_read) {
    await_all();
    return snapshot.status.ok() ? absl::DataLossError("no centroids read")
                                : snapshot.status;
  }
  if (snapshot.dimension != meta.code_dimension) {
    await_all();
    return absl::DataLossError(
        absl::StrCat("the snapshot's codes have ", snapshot.dimension,
                     " dimensions, the fleet's ", meta.code_dimension));
  }
  const absl::Time memory_start = absl::Now();
  size_t centroids_reconciled = 0;
  core::ByteReader centroids(snapshot.centroid_bytes);
  absl::Status kept_centroids = memory.RestoreAll(
      std::move(clusters), centroids, &centroids_reconciled, RunOnTwoThreads);
  *restored = true;
  if (!kept_centroids.ok()) {
    FLEETMEM_LOG(kWarning) << "fleet \"" << id
                           << "\": forgetting's centroid graph rebuilt: "
                           << kept_centroids;
  }
  const double memory_seconds =
      absl::ToDoubleSeconds(absl::Now() - memory_start);
  await_all();
  absl::Status status =
      snapshot.status.ok() ? snapshot.index_status : snapshot.status;
  if (!status.ok()) return status;
  const size_t unindexed = snapshot.unindexed;

  // Reconcile with the store: traces stored since the snapshot are added,
  // traces forgotten or downsampled since are removed.
  const absl::Time reconcile_start = absl::Now();
  absl::StatusOr<FleetIndex::Reconciled> reconciled =
      index.Reconcile(std::move(snapshot.index), std::move(snapshot.handles),
                      snapshot.next_handle, traces);
  if (!reconciled.ok()) return reconciled.status();
  if (reconciled->added == 0 && reconciled->removed == 0 &&
      centroids_reconciled == 0) {
    index.SnapshotWritten(0, unindexed);  // the snapshot on disk is this state
  }
  FLEETMEM_LOG(kInfo) << "fleet \"" << id
                      << "\": index snapshot reconciled: " << reconciled->kept
                      << " codes kept, " << reconciled->added << " added, "
                      << reconciled->removed << " removed; "
                      << centroids_reconciled << " centroids changed (handles "
                      << snapshot.handles_seconds << " s and index "
                      << snapshot.index_seconds
                      << " s beside the store's read, memory " << memory_seconds
                      << " s, reconciling "
                      << absl::ToDoubleSeconds(absl::Now() - reconcile_start)
                      << " s)";
  return absl::OkStatus();
}

absl::Status MemoryEngine::DeferIndexing(std::string_view fleet_id,
                                         absl::Time until) {
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) {
    return absl::NotFoundError(
        absl::StrCat("fleet \"", V(fleet_id), "\" does not exist"));
  }
  // writer_mu: the index is replaced only under it, and a writer of the
  // index may not run beside the change.
  absl::MutexLock writer(&fleet->writer_mu);
  absl::MutexLock lock(&fleet->mu);
  fleet->index.DeferIndexing(until);
  return absl::OkStatus();
}

bool MemoryEngine::IndexingDeferred(std::string_view fleet_id) const {
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) return false;
  absl::MutexLock lock(&fleet->mu);
  return fleet->index.deferred_until() > absl::Now();
}

absl::Status MemoryEngine::IndexDeferred(std::string_view fleet_id) {
  Fleet* fleet = Fleet::Find(*this, fleet_id);
  if (fleet == nullptr) {
    return absl::NotFoundError(
        absl::StrCat("fleet \"", V(fleet_id), "\" does not exist"));
  }
  // Under writer_mu (the index stays this one; the fleet's next apply
  // waits for the build) but not the fleet's lock: queries go on.
  absl::MutexLock writer(&fleet->writer_mu);
  PlaceIndex* index = nullptr;
  {
    absl::MutexLock lock(&fleet->mu);
    fleet->index.DeferIndexing(absl::InfinitePast());
    index = fleet->index.get();
  }
  return index == nullptr ? absl::OkStatus() : index->IndexWaiting();
}

}  // namespace fleetmem::engine
