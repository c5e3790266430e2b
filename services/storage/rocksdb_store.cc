#include "services/storage/rocksdb_store.h"

#include <fcntl.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstring>
#include <exception>
#include <filesystem>
#include <iterator>
#include <map>
#include <optional>
#include <set>
#include <span>
#include <string>
#include <system_error>
#include <utility>
#include <vector>

#include "absl/functional/function_ref.h"
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "rocksdb/cache.h"
#include "rocksdb/convenience.h"
#include "rocksdb/db.h"
#include "rocksdb/filter_policy.h"
#include "rocksdb/iterator.h"
#include "rocksdb/options.h"
#include "rocksdb/sst_file_manager.h"
#include "rocksdb/table.h"
#include "rocksdb/utilities/checkpoint.h"
#include "rocksdb/write_batch.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/storage/keys.h"
#include "services/storage/mutation_checks.h"
#include "services/storage/record_codec.h"
#include "services/storage/rocksdb_info_log.h"
#include "services/storage/segment_log.h"
#include "services/storage/snapshot_file.h"
#include "services/storage/wal_room.h"

namespace fleetmem::storage {
namespace {

using core::TraceKey;

rocksdb::Slice ToSlice(std::string_view bytes) {
  return rocksdb::Slice(bytes.data(), bytes.size());
}

std::string_view ToView(const rocksdb::Slice& slice) {
  return std::string_view(slice.data(), slice.size());
}

// The one place where RocksDB statuses become absl ones. `what` says which
// operation failed ("open '/var/lib/fleetmem'", "write fleet f1").
absl::Status FromRocksDb(const rocksdb::Status& status, std::string_view what) {
  if (status.ok()) return absl::OkStatus();
  const std::string message =
      absl::StrCat("RocksDB ", V(what), ": ", status.ToString());
  if (status.IsNoSpace()) return absl::ResourceExhaustedError(message);
  switch (status.code()) {
    case rocksdb::Status::kCorruption:
      return absl::DataLossError(message);
    case rocksdb::Status::kInvalidArgument:
      return absl::InvalidArgumentError(message);
    case rocksdb::Status::kNotFound:
      return absl::NotFoundError(message);
    case rocksdb::Status::kIOError:
    case rocksdb::Status::kBusy:
    case rocksdb::Status::kTimedOut:
    case rocksdb::Status::kTryAgain:
    case rocksdb::Status::kShutdownInProgress:
    case rocksdb::Status::kAborted:
      return absl::UnavailableError(message);
    default:
      return absl::InternalError(message);
  }
}

// Releases a snapshot when leaving a scope.
class ScopedSnapshot {
 public:
  explicit ScopedSnapshot(rocksdb::DB* db)
      : db_(db), snapshot_(db->GetSnapshot()) {}
  ~ScopedSnapshot() { db_->ReleaseSnapshot(snapshot_); }
  ScopedSnapshot(const ScopedSnapshot&) = delete;
  ScopedSnapshot& operator=(const ScopedSnapshot&) = delete;

  rocksdb::ReadOptions ReadOptions() const {
    rocksdb::ReadOptions options;
    options.snapshot = snapshot_;
    return options;
  }

 private:
  rocksdb::DB* db_;
  const rocksdb::Snapshot* snapshot_;
};

// Calls `visit(key, value)` for each key in [begin, end), ascending, until it
// returns false or an error.
absl::Status ForEachInRange(
    rocksdb::DB* db, rocksdb::ReadOptions options, std::string_view begin,
    std::string_view end,
    absl::FunctionRef<absl::StatusOr<bool>(std::string_view, std::string_view)>
        visit) {
  const rocksdb::Slice upper_bound = ToSlice(end);
  options.iterate_upper_bound = &upper_bound;
  std::unique_ptr<rocksdb::Iterator> it(db->NewIterator(options));
  for (it->Seek(ToSlice(begin)); it->Valid(); it->Next()) {
    absl::StatusOr<bool> more = visit(ToView(it->key()), ToView(it->value()));
    if (!more.ok()) return more.status();
    if (!*more) break;
  }
  return FromRocksDb(it->status(), "scan");
}

// The changes of one Apply, staged by key so that later steps read what
// earlier steps wrote; turned into one WriteBatch at the end.
class Staging {
 public:
  explicit Staging(rocksdb::DB* db) : db_(db) {}

  // The value of `key` as the mutation has left it so far; nullopt if absent.
  absl::StatusOr<std::optional<std::string>> Get(const std::string& key) {
    if (auto staged = writes_.find(key); staged != writes_.end()) {
      return staged->second;
    }
    std::string value;
    const rocksdb::Status status =
        db_->Get(rocksdb::ReadOptions(), ToSlice(key), &value);
    if (status.IsNotFound()) return std::nullopt;
    if (!status.ok()) return FromRocksDb(status, "read");
    return value;
  }

  void Put(std::string key, std::string value) {
    writes_[std::move(key)] = std::move(value);
  }
  void Delete(std::string key) { writes_[std::move(key)] = std::nullopt; }

  // Erasures first, then puts.
  rocksdb::WriteBatch ToBatch() const {
    rocksdb::WriteBatch batch;
    for (const auto& [key, value] : writes_) {
      if (!value) batch.Delete(ToSlice(key));
    }
    for (const auto& [key, value] : writes_) {
      if (value) batch.Put(ToSlice(key), ToSlice(*value));
    }
    return batch;
  }

 private:
  rocksdb::DB* db_;
  std::map<std::string, std::optional<std::string>> writes_;
};

// Runs one FleetMutation against a Staging (see the rules in the header).
class MutationWriter {
 public:
  MutationWriter(std::string_view fleet_id, Staging* staging)
      : fleet_id_(fleet_id), staging_(staging) {}

  absl::Status Run(const engine::FleetMutation& m) {
    for (const core::Cluster& cluster : m.put_clusters) {
      for (const core::MemoryTrace& trace : cluster.traces) {
        if (trace.code.empty()) codes_kept_.insert(trace.key());
      }
    }
    for (const TraceKey& key : m.erase_pending) {
      staging_->Delete(keys::PendingKey(fleet_id_, key));
    }
    for (uint64_t id : m.erase_clusters) {
      if (absl::Status status = EraseCluster(id); !status.ok()) return status;
    }
    for (const TraceKey& key : m.erase_traces) {
      if (absl::Status status = EraseTrace(key); !status.ok()) return status;
    }
    if (m.put_meta) staging_->Put(keys::MetaKey(fleet_id_), EncodeMeta(m.meta));
    for (const core::MemoryTrace& trace : m.put_pending) {
      staging_->Put(keys::PendingKey(fleet_id_, trace.key()),
                    EncodeTrace(trace));
    }
    for (const core::Cluster& cluster : m.put_clusters) {
      if (absl::Status status = PutCluster(cluster); !status.ok()) {
        return status;
      }
    }
    for (const core::MemoryTrace& trace : m.update_traces) {
      if (absl::Status status = UpdateTrace(trace, m.update_traces_held);
          !status.ok()) {
        return status;
      }
    }
    for (const engine::RobotRecord& robot : m.put_robots) {
      staging_->Put(keys::RobotKey(fleet_id_, robot.robot_id),
                    EncodeRobot(robot));
    }
    for (const core::MemoryEvent& event : m.append_events) {
      staging_->Put(keys::EventKey(fleet_id_, event.id), EncodeEvent(event));
    }
    return absl::OkStatus();
  }

 private:
  absl::StatusOr<std::optional<StoredCluster>> GetCluster(uint64_t id) {
    const std::string key = keys::ClusterKey(fleet_id_, id);
    absl::StatusOr<std::optional<std::string>> value = staging_->Get(key);
    if (!value.ok()) return value.status();
    if (!value->has_value()) return std::nullopt;
    absl::StatusOr<StoredCluster> cluster = DecodeCluster(key, **value);
    if (!cluster.ok()) return cluster.status();
    return std::move(*cluster);
  }

  absl::StatusOr<std::optional<core::MemoryTrace>> GetTrace(
      const TraceKey& trace_key) {
    const std::string key = keys::TraceKey(fleet_id_, trace_key);
    absl::StatusOr<std::optional<std::string>> value = staging_->Get(key);
    if (!value.ok()) return value.status();
    if (!value->has_value()) return std::nullopt;
    absl::StatusOr<core::MemoryTrace> trace = DecodeTrace(key, **value);
    if (!trace.ok()) return trace.status();
    return std::move(*trace);
  }

  // A static-memory trace: its record, and its code under a key of its own
  // (keys.h); without a code, the record alone (the caller has made sure
  // that a code is stored).
  void PutTrace(const core::MemoryTrace& trace) {
    PutTraceRecord(trace);
    if (trace.code.empty()) return;
    staging_->Put(keys::CodeKey(fleet_id_, trace.key()),
                  EncodeCode(trace.code));
  }
  // The record alone: an update never changes a trace's code
  // (FleetMutation::update_traces), so a replay draw or a reward update
  // writes ~150 bytes a trace, not its 1 KB code again.
  void PutTraceRecord(const core::MemoryTrace& trace) {
    staging_->Put(keys::TraceKey(fleet_id_, trace.key()),
                  EncodeTraceWithoutCode(trace));
  }
  // Erases a stored trace (the callers know it is stored: a member of a
  // stored cluster, or a record read), its code too unless a put cluster
  // takes the trace without one: that code stays, and the put finds it.
  void DeleteTrace(const TraceKey& key) {
    staging_->Delete(keys::TraceKey(fleet_id_, key));
    if (codes_kept_.contains(key)) {
      code_stored_.insert(key);
      return;
    }
    staging_->Delete(keys::CodeKey(fleet_id_, key));
  }

  void PutClusterRecord(const StoredCluster& cluster) {
    staging_->Put(keys::ClusterKey(fleet_id_, cluster.id),
                  EncodeCluster(cluster));
  }

  // Removes `key` from the member list of cluster `cluster_id`, if stored.
  absl::Status DropMember(uint64_t cluster_id, const TraceKey& key) {
    absl::StatusOr<std::optional<StoredCluster>> cluster =
        GetCluster(cluster_id);
    if (!cluster.ok()) return cluster.status();
    if (!cluster->has_value()) return absl::OkStatus();
    std::erase((*cluster)->members, key);
    PutClusterRecord(**cluster);
    return absl::OkStatus();
  }

  absl::Status EraseCluster(uint64_t id) {
    absl::StatusOr<std::optional<StoredCluster>> cluster = GetCluster(id);
    if (!cluster.ok()) return cluster.status();
    if (!cluster->has_value()) return absl::OkStatus();
    for (const TraceKey& member : (*cluster)->members) DeleteTrace(member);
    staging_->Delete(keys::ClusterKey(fleet_id_, id));
    return absl::OkStatus();
  }

  absl::Status EraseTrace(const TraceKey& key) {
    absl::StatusOr<std::optional<core::MemoryTrace>> trace = GetTrace(key);
    if (!trace.ok()) return trace.status();
    if (!trace->has_value()) return absl::OkStatus();
    DeleteTrace(key);
    return DropMember((*trace)->cluster_id, key);
  }

  absl::Status PutCluster(const core::Cluster& cluster) {
    std::set<TraceKey> keep;
    for (const core::MemoryTrace& trace : cluster.traces) {
      keep.insert(trace.key());
    }
    absl::StatusOr<std::optional<StoredCluster>> old = GetCluster(cluster.id);
    if (!old.ok()) return old.status();
    if (old->has_value()) {
      for (const TraceKey& member : (*old)->members) {
        if (!keep.contains(member)) DeleteTrace(member);
      }
    }
    StoredCluster stored{cluster.id, cluster.robot_id, cluster.centroid, {}};
    stored.members.reserve(cluster.traces.size());
    for (const core::MemoryTrace& trace : cluster.traces) {
      absl::StatusOr<std::optional<core::MemoryTrace>> existing =
          GetTrace(trace.key());
      if (!existing.ok()) return existing.status();
      if (existing->has_value() && (*existing)->cluster_id != cluster.id) {
        if (absl::Status status =
                DropMember((*existing)->cluster_id, trace.key());
            !status.ok()) {
          return status;
        }
      }
      if (trace.code.empty() && !existing->has_value() &&
          !code_stored_.contains(trace.key())) {
        return internal::NoStoredCode(trace, cluster.id);
      }
      core::MemoryTrace copy = trace;
      copy.cluster_id = cluster.id;
      PutTrace(copy);
      stored.members.push_back(trace.key());
    }
    PutClusterRecord(stored);
    return absl::OkStatus();
  }

  absl::Status UpdateTrace(const core::MemoryTrace& trace, bool held) {
    // Vouched for by the engine (FleetMutation::update_traces_held): written
    // as it is, without reading the record first (a replay draw of 1,000
    // traces read 1,000 records only to keep their cluster ids, half of the
    // draw's time: issue 48's replay benchmark).
    if (held && trace.cluster_id != 0) {
      PutTraceRecord(trace);
      return absl::OkStatus();
    }
    absl::StatusOr<std::optional<core::MemoryTrace>> existing =
        GetTrace(trace.key());
    if (!existing.ok()) return existing.status();
    if (!existing->has_value()) return absl::OkStatus();
    core::MemoryTrace copy = trace;
    copy.cluster_id = (*existing)->cluster_id;
    PutTraceRecord(copy);
    return absl::OkStatus();
  }

  std::string_view fleet_id_;
  Staging* staging_;
  // Put clusters' traces that come without a code (the stored one stays).
  std::set<TraceKey> codes_kept_;
  // Those of them this mutation's erasures found stored.
  std::set<TraceKey> code_stored_;
};

// How a write waits for RocksDB to recover from a background error: up to
// kResumeAttempts x kResumeInterval = 8 s. RocksDB's recovery from a
// no-space error is driven by its SstFileManager, which re-checks the free
// space every 5 s; other retryable errors are resumed every kResumeInterval
// (see MakeOptions).
constexpr int kResumeAttempts = 40;
// Entries per read when moving an earlier build's log out of RocksDB.
constexpr size_t kLegacyPage = 64;
// A load of this many traces or more logs where its time went.
constexpr size_t kLoadLoggedFrom = 10'000;
// Traces per write when moving codes out of their records (MigrateCodes).
constexpr uint64_t kMigrationBatch = 4096;

// Records the current key layout (synced).
absl::Status WriteFormat(rocksdb::DB* db, const std::string& path) {
  rocksdb::WriteOptions write;
  write.sync = true;
  return FromRocksDb(
      db->Put(write, ToSlice(keys::kFormatKey), ToSlice(keys::kFormatVersion)),
      absl::StrCat("write format version at '", path, "'"));
}
constexpr absl::Duration kResumeInterval = absl::Milliseconds(200);

absl::StatusOr<uint64_t> StatvfsFreeBytes(const std::string& path) {
  struct statvfs info;
  if (statvfs(path.c_str(), &info) != 0) {
    return absl::UnavailableError(
        absl::StrCat("statvfs '", path, "': ", std::strerror(errno)));
  }
  return static_cast<uint64_t>(info.f_bavail) * info.f_frsize;
}

// The reserve file (PATH.reserve): half of min_free_bytes more, held as a
// file from the first open or write that finds room for it above
// min_free_bytes,
// for an open on a filesystem another process has filled: Open gives it
// back first, so that RocksDB's recovery (a new write-ahead log, the
// manifest, a flush) finds room. Debian's RocksDB asserts on a failed
// write-ahead-log write: such a restart aborted at open before. Writes
// still stop at min_free_bytes free; the file is taken again once there is
// room for it above that.
std::string ReservePath(const std::string& path) { return path + ".reserve"; }

bool CreateReserve(const std::string& file, uint64_t bytes) {
  const int fd = open(file.c_str(), O_WRONLY | O_CREAT | O_CLOEXEC, 0600);
  if (fd < 0) return false;
  const bool made = posix_fallocate(fd, 0, static_cast<off_t>(bytes)) == 0 &&
                    fdatasync(fd) == 0;
  close(fd);
  if (!made) unlink(file.c_str());
  return made;
}

bool HasReserve(const std::string& file) {
  return access(file.c_str(), F_OK) == 0;
}

// The Env RocksDB writes through (wal_room.h): a write-ahead-log or
// manifest append that meets a full disk gives back the reserve file and,
// if that is not enough, waits for space rather than failing (a failed
// append is what made Debian's RocksDB abort later). `given_back` is set
// when it took the reserve file.
std::unique_ptr<rocksdb::Env> MakeEnv(
    const std::string& path, std::shared_ptr<std::atomic<bool>> given_back) {
  WalRoomOptions room;
  room.give_back = [reserve = ReservePath(path), given_back] {
    if (unlink(reserve.c_str()) != 0) return false;
    given_back->store(true);
    FLEETMEM_LOG(kError) << "disk full under a RocksDB write: reserve file "
                         << reserve
                         << " given back so that it completes; writes are "
                            "refused until space is freed";
    return true;
  };
  return rocksdb::NewCompositeEnv(NewWalRoomFileSystem(std::move(room)));
}

// A mark's value (keys.h: 's'), and the clean close's record (its stamp
// only): stamp and digest, 8 bytes each.
std::string EncodeMark(const SnapshotFileId& id) {
  std::string value(16, '\0');
  std::memcpy(value.data(), &id.stamp, 8);
  std::memcpy(value.data() + 8, &id.digest, 8);
  return value;
}

std::optional<SnapshotFileId> DecodeMark(std::string_view value) {
  if (value.size() != 16) return std::nullopt;
  SnapshotFileId id;
  std::memcpy(&id.stamp, value.data(), 8);
  std::memcpy(&id.digest, value.data() + 8, 8);
  return id;
}

class RocksDbStore final : public engine::MemoryStore {
 public:
  RocksDbStore(std::unique_ptr<rocksdb::Env> env,
               std::shared_ptr<std::atomic<bool>> reserve_given_back,
               std::unique_ptr<rocksdb::DB> db,
               const RocksDbStoreOptions& options)
      : env_(std::move(env)),
        reserve_given_back_(std::move(reserve_given_back)),
        db_(std::move(db)),
        path_(options.path),
        min_free_bytes_(options.min_free_bytes),
        free_bytes_(options.free_bytes ? options.free_bytes : StatvfsFreeBytes),
        // Only on a real filesystem: an injected free-space count would not
        // see the file.
        reserve_bytes_(options.free_bytes ? 0 : options.min_free_bytes / 2),
        reserve_held_(reserve_bytes_ > 0 && HasReserve(ReservePath(path_))) {
    write_options_.sync = options.sync;
    synced_write_options_.sync = true;
    unsynced_write_options_.sync = false;
  }

  ~RocksDbStore() override {
    // The sequence number before this last write: a start that finds one
    // past it knows that nothing wrote the store since (LoadSnapshotMarks).
    const std::string closed =
        EncodeMark({.stamp = db_->GetLatestSequenceNumber(), .digest = 0});
    const rocksdb::Status put = db_->Put(
        synced_write_options_, ToSlice(keys::kClosedKey), ToSlice(closed));
    if (!put.ok()) {
      FLEETMEM_LOG(kWarning)
          << "RocksDB at " << path_ << ": no record of the clean close ("
          << put.ToString() << "); the next start reads every fleet";
    }
    // No iterator or snapshot outlives a call, so the database can close.
    const rocksdb::Status status = db_->Close();
    if (!status.ok()) {
      FLEETMEM_LOG(kWarning)
          << "closing RocksDB at " << path_ << ": " << status.ToString();
    }
  }

  absl::Status Checkpoint(const std::string& directory) override {
    rocksdb::Checkpoint* raw = nullptr;
    rocksdb::Status status = rocksdb::Checkpoint::Create(db_.get(), &raw);
    if (!status.ok()) return FromRocksDb(status, "create checkpoint");
    std::unique_ptr<rocksdb::Checkpoint> checkpoint(raw);
    // log_size_for_flush 0: the memtables are flushed first, so the copy is
    // SST files (hard links where possible) and needs no WAL replay. RocksDB
    // removes its temporary directory itself when this fails.
    // The ingest log is copied after RocksDB, no trim between: the copy
    // holds every entry the checkpoint has not applied.
    bool created = false;
    absl::Status copied = log_->CopyTo(directory + "/ingest-log", [&] {
      absl::Status made = FromRocksDb(
          checkpoint->CreateCheckpoint(directory, /*log_size_for_flush=*/0),
          absl::StrCat("checkpoint to ", directory));
      created = made.ok();
      return made;
    });
    if (!copied.ok() && created) {
      std::error_code ignored;
      std::filesystem::remove_all(directory, ignored);
    }
    return copied;
  }

  absl::Status SaveIndexSnapshot(
      std::string_view fleet_id,
      const std::function<absl::Status(core::ByteWriter&)>& write,
      const std::function<void()>& written) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    std::error_code error;
    std::filesystem::create_directories(SnapshotDirectory(), error);
    if (error) {
      return absl::UnavailableError(
          absl::StrCat("no index snapshot written: cannot create '",
                       SnapshotDirectory(), "': ", error.message()));
    }
    // Stamped with the state before `write` reads memory (for the log: the
    // engine reconciles the snapshot with what the store holds at load).
    // A snapshot must not eat into the reserve that keeps the database
    // writable (its next open may need to flush the write-ahead log).
    auto check_room = [this]() -> absl::Status {
      if (min_free_bytes_ == 0) return absl::OkStatus();
      absl::StatusOr<uint64_t> free = free_bytes_(path_);
      if (!free.ok()) return free.status();
      if (*free < min_free_bytes_ + (uint64_t{2} << 20)) {
        return absl::ResourceExhaustedError(
            absl::StrCat("disk nearly full: ", *free,
                         " bytes free, the reserve is ", min_free_bytes_));
      }
      return absl::OkStatus();
    };
    // Once the bytes are in the file and before the caller lets writes in
    // again, the mark names it: the fleet's next write deletes it.
    const uint64_t stamp = db_->GetLatestSequenceNumber();
    auto mark = [&](uint64_t digest) {
      PutMark(fleet_id, {.stamp = stamp, .digest = digest});
      if (written) written();
    };
    return WriteSnapshotFile(SnapshotDirectory(), fleet_id, stamp, write,
                             check_room, mark);
  }

  bool IndexSnapshotCurrent(std::string_view fleet_id) override {
    std::optional<SnapshotFileId> mark;
    {
      absl::ReaderMutexLock lock(&marks_mu_);
      auto it = marks_.find(fleet_id);
      if (it == marks_.end()) return false;
      mark = it->second;
    }
    absl::StatusOr<SnapshotFileId> file =
        ReadSnapshotFileId(SnapshotDirectory(), fleet_id);
    return file.ok() && *file == *mark;
  }

  absl::Status ReadIndexSnapshot(
      std::string_view fleet_id,
      const engine::IndexSnapshotRead& read) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    uint64_t stamp = 0;
    absl::Status status =
        ReadSnapshotFile(SnapshotDirectory(), fleet_id, read, &stamp);
    if (status.ok()) {
      const uint64_t now = db_->GetLatestSequenceNumber();
      FLEETMEM_LOG(kInfo) << "index snapshot of fleet \"" << fleet_id
                          << "\" was written at store sequence " << stamp
                          << " (now " << now << ")";
    }
    return status;
  }

  uint64_t ApproximateDiskBytes() override {
    uint64_t sst = 0;
    uint64_t memtables = 0;
    db_->GetIntProperty(rocksdb::DB::Properties::kLiveSstFilesSize, &sst);
    db_->GetIntProperty(rocksdb::DB::Properties::kCurSizeAllMemTables,
                        &memtables);
    return sst + memtables + log_->Bytes() + log_->SpareBytes();
  }

  std::vector<std::pair<std::string, uint64_t>> MemoryUsage() override {
    std::vector<std::pair<std::string, uint64_t>> usage;
    auto add = [&](const char* kind, const std::string& property) {
      uint64_t bytes = 0;
      if (db_->GetIntProperty(property, &bytes))
        usage.emplace_back(kind, bytes);
    };
    // Active, unflushed and pinned memtables.
    add("memtables", rocksdb::DB::Properties::kSizeAllMemTables);
    // Index and filter blocks of the open table files (not in the block
    // cache: cache_index_and_filter_blocks is off), growing with the data.
    add("table_readers", rocksdb::DB::Properties::kEstimateTableReadersMem);
    add("block_cache", rocksdb::DB::Properties::kBlockCacheUsage);
    add("block_cache_pinned", rocksdb::DB::Properties::kBlockCachePinnedUsage);
    return usage;
  }

  absl::StatusOr<std::vector<std::string>> ListFleets() override {
    std::set<std::string> fleets;
    for (keys::Tag tag : keys::kFleetTags) {
      absl::Status listed = ForEachFleet(
          tag, [&](std::string_view fleet_id) { fleets.emplace(fleet_id); });
      if (!listed.ok()) return listed;
    }
    return std::vector<std::string>(fleets.begin(), fleets.end());
  }

  absl::StatusOr<engine::FleetRecord> LoadFleet(
      std::string_view fleet_id) override {
    return LoadFleetWithoutHeldCodes(fleet_id, nullptr);
  }

  absl::StatusOr<engine::FleetRecord> LoadFleetWithoutClusters(
      std::string_view fleet_id) override {
    return Load(fleet_id, /*clusters=*/false, nullptr);
  }

  absl::StatusOr<engine::FleetRecord> LoadFleetWithoutHeldCodes(
      std::string_view fleet_id,
      const std::function<bool(const TraceKey&)>& code_held_elsewhere)
      override {
    return Load(fleet_id, /*clusters=*/true, code_held_elsewhere);
  }

  // LoadFleet; without the clusters and their traces if `clusters` is
  // false.
  absl::StatusOr<engine::FleetRecord> Load(
      std::string_view fleet_id, bool clusters,
      const std::function<bool(const TraceKey&)>& code_held_elsewhere) {
    engine::FleetRecord record;
    record.fleet_id = std::string(fleet_id);
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    ScopedSnapshot snapshot(db_.get());
    rocksdb::ReadOptions read = snapshot.ReadOptions();
    // A load reads the whole fleet once (1.2 GB at 1,000,000 256-d traces);
    // through the 64 MB block cache it only churns it. Without: the store
    // read of 1,000,000 traces went from 3.3-3.5 s to 2.4-2.6 s.
    read.fill_cache = false;

    const std::string meta_key = keys::MetaKey(fleet_id);
    std::string value;
    const rocksdb::Status got = db_->Get(read, ToSlice(meta_key), &value);
    if (got.ok()) {
      absl::StatusOr<engine::FleetMeta> meta = DecodeMeta(meta_key, value);
      if (!meta.ok()) return meta.status();
      record.meta = std::move(*meta);
    } else if (!got.IsNotFound()) {
      return FromRocksDb(got, absl::StrCat("load fleet ", V(fleet_id)));
    }

    absl::Status status =
        Scan(read, keys::Tag::kPending, fleet_id,
             [&](std::string_view key, std::string_view v) {
               return Append(DecodeTrace(key, v), &record.pending);
             });
    if (!status.ok()) return status;
    status = Scan(read, keys::Tag::kRobot, fleet_id,
                  [&](std::string_view key, std::string_view v) {
                    return Append(DecodeRobot(key, v), &record.robots);
                  });
    if (!status.ok()) return status;
    if (!clusters) return record;

    // The records first (~150 bytes a trace), then the codes they need:
    // those `code_held_elsewhere` leaves to the store, by one pass over the
    // codes in key order that seeks past the rest.
    TraceTable traces;
    const absl::Time start = absl::Now();
    status = Scan(read, keys::Tag::kTrace, fleet_id,
                  [&](std::string_view key, std::string_view v) {
                    absl::StatusOr<core::MemoryTrace> trace =
                        DecodeTrace(key, v);
                    if (!trace.ok()) return trace.status();
                    traces.Add(*std::move(trace));
                    return absl::OkStatus();
                  });
    if (!status.ok()) return status;
    const absl::Time records_read = absl::Now();
    size_t codes_read = 0;
    status =
        ReadCodes(read, fleet_id, code_held_elsewhere, traces, &codes_read);
    if (!status.ok()) return status;
    const absl::Time codes_done = absl::Now();
    const size_t trace_count = traces.size();
    status = Scan(read, keys::Tag::kCluster, fleet_id,
                  [&](std::string_view key, std::string_view v) {
                    absl::StatusOr<StoredCluster> stored =
                        DecodeCluster(key, v);
                    if (!stored.ok()) return stored.status();
                    return AssembleCluster(key, std::move(*stored), &traces,
                                           &record.clusters);
                  });
    if (!status.ok()) return status;
    if (const core::MemoryTrace* orphan = traces.AnyLeft()) {
      return absl::DataLossError(
          absl::StrCat("corrupt record at ",
                       keys::Describe(keys::TraceKey(fleet_id, orphan->key())),
                       ": trace of cluster ", orphan->cluster_id,
                       " which does not list it"));
    }
    if (trace_count >= kLoadLoggedFrom) {
      FLEETMEM_LOG(kInfo) << "fleet \"" << fleet_id << "\": read "
                          << trace_count << " trace records in "
                          << absl::ToDoubleSeconds(records_read - start)
                          << " s, " << codes_read << " codes in "
                          << absl::ToDoubleSeconds(codes_done - records_read)
                          << " s, " << record.clusters.size() << " clusters in "
                          << absl::ToDoubleSeconds(absl::Now() - codes_done)
                          << " s";
    }
    return record;
  }

  absl::Status Apply(std::string_view fleet_id,
                     const engine::FleetMutation& mutation) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    if (absl::Status status = internal::CheckMutation(mutation); !status.ok()) {
      return status;
    }
    // Serialised: the staged reads must see every earlier Apply's writes and
    // no concurrent one's.
    absl::MutexLock lock(&apply_mu_);
    Staging staging(db_.get());
    if (absl::Status status = MutationWriter(fleet_id, &staging).Run(mutation);
        !status.ok()) {
      return status;
    }
    rocksdb::WriteBatch batch = staging.ToBatch();
    if (mutation.erase_events_before > 1) {
      // Event retention: one range tombstone for every older event.
      batch.DeleteRange(
          ToSlice(keys::EventKey(fleet_id, 0)),
          ToSlice(keys::EventKey(fleet_id, mutation.erase_events_before)));
    }
    if (batch.Count() == 0) return absl::OkStatus();
    return Write(fleet_id, batch,
                 mutation.sync ? write_options_ : unsynced_write_options_,
                 "write fleet");
  }

  absl::Status DeleteFleet(std::string_view fleet_id,
                           const engine::FleetMeta& kept) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    std::vector<std::pair<std::string, std::string>> ranges;
    for (keys::Tag tag : keys::kFleetTags) {
      ranges.emplace_back(keys::Prefix(tag, fleet_id),
                          keys::PrefixEnd(tag, fleet_id));
    }
    // Entries older builds kept in RocksDB (OpenLog moved them out).
    ranges.emplace_back(keys::Prefix(keys::Tag::kLog, fleet_id),
                        keys::PrefixEnd(keys::Tag::kLog, fleet_id));
    ranges.emplace_back(keys::Prefix(keys::Tag::kSnapshotMark, fleet_id),
                        keys::PrefixEnd(keys::Tag::kSnapshotMark, fleet_id));
    rocksdb::WriteBatch batch;
    for (const auto& [begin, end] : ranges) {
      batch.DeleteRange(ToSlice(begin), ToSlice(end));
    }
    // After the range tombstones in the batch: the meta stays.
    const std::string meta = EncodeMeta(kept);
    batch.Put(ToSlice(keys::MetaKey(fleet_id)), ToSlice(meta));
    {
      absl::MutexLock lock(&apply_mu_);
      absl::Status written =
          Write(fleet_id, batch, write_options_, "delete fleet");
      if (!written.ok()) return written;
    }
    std::error_code error;
    std::filesystem::remove(
        SnapshotFilePath(SnapshotDirectory(), std::string(fleet_id)), error);
    if (error) {
      FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                             << "\" deleted; its index snapshot stays on disk: "
                             << error.message();
    }
    // The data leaves the disk now, not at some later compaction: the
    // ranges' table files are rewritten without what the tombstones cover.
    std::vector<keys::Tag> tags(std::begin(keys::kFleetTags),
                                std::end(keys::kFleetTags));
    tags.push_back(keys::Tag::kLog);
    CompactRanges(fleet_id, tags);
    return absl::OkStatus();
  }

  absl::StatusOr<std::vector<engine::FleetAlias>> LoadAliases() override {
    std::vector<engine::FleetAlias> aliases;
    const std::string first(1, static_cast<char>(keys::Tag::kAlias));
    const std::string end(1, static_cast<char>(keys::Tag::kAlias) + 1);
    absl::Status read = ForEachInRange(
        db_.get(), rocksdb::ReadOptions(), first, end,
        [&](std::string_view key,
            std::string_view value) -> absl::StatusOr<bool> {
          const std::optional<keys::ParsedKey> parsed = keys::Parse(key);
          if (!parsed || !parsed->suffix.empty() || value.empty()) {
            return absl::DataLossError(
                absl::StrCat("malformed alias in RocksDB at ", path_, ": ",
                             keys::Describe(key)));
          }
          aliases.push_back(
              {std::string(parsed->fleet_id), std::string(value)});
          return true;
        });
    if (!read.ok()) return read;
    return aliases;
  }

  absl::Status PutAlias(std::string_view alias,
                        std::string_view fleet_id) override {
    if (absl::Status status = internal::CheckFleetId(alias); !status.ok()) {
      return status;
    }
    rocksdb::WriteBatch batch;
    const std::string key = keys::AliasKey(alias);
    if (fleet_id.empty()) {
      batch.Delete(ToSlice(key));
    } else {
      batch.Put(ToSlice(key), ToSlice(fleet_id));
    }
    absl::MutexLock lock(&apply_mu_);
    return Write(alias, batch, write_options_, "write alias");
  }

  // The ingest log: segment files beside RocksDB's (segment_log.h says
  // why), owned by the store because the two keep each other's rules: a
  // trim syncs the store's write-ahead log first, an append keeps the
  // store's disk reserve, and a checkpoint copies both.
  engine::FleetLog* log() { return log_.get(); }

  // Reads the marks (keys.h: 's') at open, before anything writes: kept if
  // the last write was the clean close's record, so that none was written
  // since by a build that does not delete them (an older one) or lost with
  // a crash; else deleted, every one, so that they cannot outlive a write
  // this start does not know of.
  absl::Status LoadSnapshotMarks() {
    std::string value;
    const rocksdb::Status got =
        db_->Get(rocksdb::ReadOptions(), ToSlice(keys::kClosedKey), &value);
    if (!got.ok() && !got.IsNotFound()) {
      return FromRocksDb(got, "read the clean close's record");
    }
    const std::optional<SnapshotFileId> closed =
        got.ok() ? DecodeMark(value) : std::nullopt;
    const bool trusted =
        closed && closed->stamp + 1 == db_->GetLatestSequenceNumber();
    const std::string begin(1, static_cast<char>(keys::Tag::kSnapshotMark));
    const std::string end(1, static_cast<char>(keys::Tag::kSnapshotMark) + 1);
    std::map<std::string, SnapshotFileId, std::less<>> marks;
    absl::Status read = ForEachInRange(
        db_.get(), rocksdb::ReadOptions(), begin, end,
        [&](std::string_view key,
            std::string_view mark) -> absl::StatusOr<bool> {
          const std::optional<keys::ParsedKey> parsed = keys::Parse(key);
          const std::optional<SnapshotFileId> id = DecodeMark(mark);
          if (parsed && id) marks[std::string(parsed->fleet_id)] = *id;
          return true;
        });
    if (!read.ok()) return read;
    if (trusted || marks.empty()) {
      absl::MutexLock lock(&marks_mu_);
      marks_ = std::move(marks);
      return absl::OkStatus();
    }
    FLEETMEM_LOG(kInfo) << "RocksDB at " << path_
                        << ": not closed cleanly by this build last time; "
                           "fleets are read from the store, not from their "
                           "index snapshots' memory";
    rocksdb::WriteBatch batch;
    batch.DeleteRange(ToSlice(begin), ToSlice(end));
    return FromRocksDb(db_->Write(synced_write_options_, &batch),
                       "delete the index snapshots' marks");
  }

  // Records that `fleet_id`'s index snapshot is the file `id`; a failure is
  // logged (the next load then reads the fleet from the store).
  void PutMark(std::string_view fleet_id, const SnapshotFileId& id) {
    absl::MutexLock marks(&marks_mu_);
    const std::string value = EncodeMark(id);
    const rocksdb::Status put =
        db_->Put(unsynced_write_options_,
                 ToSlice(keys::SnapshotMarkKey(fleet_id)), ToSlice(value));
    if (!put.ok()) {
      FLEETMEM_LOG(kWarning) << "fleet \"" << fleet_id
                             << "\": its index snapshot is not marked current ("
                             << put.ToString() << ")";
      return;
    }
    marks_[std::string(fleet_id)] = id;
  }

  // LoadSnapshotMarks, then OpenLog: the marks before anything writes.
  absl::Status OpenMarksAndLog() {
    if (absl::Status marks = LoadSnapshotMarks(); !marks.ok()) return marks;
    return OpenLog();
  }

  // Opens the ingest log at PATH/ingest-log and moves into it the entries
  // that builds before it kept in RocksDB (their keys are then erased).
  absl::Status OpenLog() {
    SegmentLogOptions options;
    options.directory = path_ + "/ingest-log";
    options.check_room = [this](std::string_view fleet_id, uint64_t bytes) {
      return CheckRoom(fleet_id, bytes);
    };
    // A trimmed entry must not outlive what it was applied to, and the
    // applies of log entries are written unsynced (FleetMutation::sync):
    // sync RocksDB's write-ahead log before segments go (once a segment).
    options.before_trim = [this]() -> absl::Status {
      return FromRocksDb(db_->FlushWAL(/*sync=*/true),
                         "sync the write-ahead log before trimming the "
                         "ingest log");
    };
    absl::StatusOr<std::unique_ptr<SegmentLog>> log =
        SegmentLog::Open(std::move(options));
    if (!log.ok()) return log.status();
    log_ = *std::move(log);
    return MoveLegacyLog();
  }

  absl::StatusOr<std::vector<core::MemoryEvent>> ReadEvents(
      std::string_view fleet_id, uint64_t after_event, size_t limit) override {
    if (absl::Status status = internal::CheckFleetId(fleet_id); !status.ok()) {
      return status;
    }
    std::vector<core::MemoryEvent> events;
    if (limit == 0 || after_event == UINT64_MAX) return events;
    const absl::Status status = ForEachInRange(
        db_.get(), rocksdb::ReadOptions(),
        keys::EventKey(fleet_id, after_event + 1),
        keys::PrefixEnd(keys::Tag::kEvent, fleet_id),
        [&](std::string_view key,
            std::string_view value) -> absl::StatusOr<bool> {
          absl::StatusOr<core::MemoryEvent> event = DecodeEvent(key, value);
          if (!event.ok()) return event.status();
          events.push_back(std::move(*event));
          return events.size() < limit;
        });
    if (!status.ok()) return status;
    return events;
  }

  // Layout 1 -> 2 (keys.h): moves each static-memory trace's code out of
  // its record to a key of its own, kMigrationBatch traces a write, then
  // records layout 2. A crash in between leaves records of both layouts,
  // which a load reads alike (a record that still holds its code is used as
  // it is), and the next open carries on. A one-off: ~1.2 GB rewritten at
  // 1,000,000 256-d traces.
  absl::Status MigrateCodes() {
    absl::StatusOr<std::vector<std::string>> fleets =
        FleetsWith(keys::Tag::kTrace);
    if (!fleets.ok()) return fleets.status();
    for (const std::string& fleet : *fleets) {
      const absl::Time start = absl::Now();
      uint64_t moved = 0;
      rocksdb::WriteBatch batch;
      auto flush = [&]() -> absl::Status {
        if (batch.Count() == 0) return absl::OkStatus();
        absl::Status written =
            Write(fleet, batch, unsynced_write_options_, "migrate codes of");
        batch.Clear();
        return written;
      };
      absl::Status status = Scan(
          rocksdb::ReadOptions(), keys::Tag::kTrace, fleet,
          [&](std::string_view key, std::string_view value) -> absl::Status {
            absl::StatusOr<core::MemoryTrace> trace = DecodeTrace(key, value);
            if (!trace.ok()) return trace.status();
            if (trace->code.empty()) return absl::OkStatus();  // moved
            batch.Put(ToSlice(key), EncodeTraceWithoutCode(*trace));
            batch.Put(ToSlice(keys::CodeKey(fleet, trace->key())),
                      EncodeCode(trace->code));
            if (++moved % kMigrationBatch == 0) return flush();
            return absl::OkStatus();
          });
      if (status.ok()) status = flush();
      if (!status.ok()) return status;
      // The records' earlier versions leave the disk now, not at some
      // later compaction (they are most of the fleet's bytes).
      constexpr keys::Tag kMigrated[] = {keys::Tag::kTrace, keys::Tag::kCode};
      CompactRanges(fleet, kMigrated);
      FLEETMEM_LOG(kInfo) << "fleet \"" << fleet << "\": moved the codes of "
                          << moved << " traces to keys of their own in "
                          << absl::ToDoubleSeconds(absl::Now() - start)
                          << " s (store layout 2)";
    }
    if (absl::Status synced = FromRocksDb(db_->FlushWAL(/*sync=*/true),
                                          "sync the migrated records");
        !synced.ok()) {
      return synced;
    }
    return WriteFormat(db_.get(), path_);
  }

  // At open: the reserve file is taken now if there is room, so that a
  // store never written to can open again on a filesystem filled since.
  void TakeReserveAtOpen() {
    if (reserve_bytes_ == 0) return;
    absl::StatusOr<uint64_t> free = free_bytes_(path_);
    if (!free.ok()) return;
    absl::MutexLock reserve(&reserve_mu_);
    TakeReserve(*free);
  }

 private:
  // Moves log entries that an earlier build kept in RocksDB (keys::LogKey)
  // into the segment log, each fleet's then erased from RocksDB (synced). A
  // crash in between leaves them in both: the entries already moved are
  // skipped when this runs again.
  absl::Status MoveLegacyLog() {
    absl::StatusOr<std::vector<std::string>> fleets =
        FleetsWith(keys::Tag::kLog);
    if (!fleets.ok()) return fleets.status();
    for (const std::string& fleet : *fleets) {
      absl::StatusOr<engine::LogBounds> moved = log_->Bounds(fleet);
      if (!moved.ok()) return moved.status();
      uint64_t after = moved->last;
      uint64_t entries = 0;
      while (true) {
        std::vector<engine::LogEntry> page;
        const absl::Status read = ForEachInRange(
            db_.get(), rocksdb::ReadOptions(), keys::LogKey(fleet, after + 1),
            keys::PrefixEnd(keys::Tag::kLog, fleet),
            [&](std::string_view key,
                std::string_view value) -> absl::StatusOr<bool> {
              absl::StatusOr<engine::LogEntry> entry =
                  DecodeLoggedUpload(key, value);
              if (!entry.ok()) return entry.status();
              page.push_back(*std::move(entry));
              return page.size() < kLegacyPage;
            });
        if (!read.ok()) return read;
        if (page.empty()) break;
        // One append per entry, each under its own sequence (the
        // engine's position counts them; a gap stays a gap).
        for (const engine::LogEntry& entry : page) {
          const engine::LogAppend append{entry.view()};
          absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
              log_->Append(fleet, {&append, 1}, {.above = entry.sequence - 1});
          if (!appended.ok()) return appended.status();
          if (appended->front().sequence != entry.sequence) {
            return absl::DataLossError(absl::StrCat(
                "moving the ingest log of fleet \"", fleet, "\": entry ",
                entry.sequence, " would become ", appended->front().sequence,
                " (the log is ahead of it)"));
          }
        }
        entries += page.size();
        after = page.back().sequence;
      }
      rocksdb::WriteBatch batch;
      batch.DeleteRange(ToSlice(keys::LogKey(fleet, 0)),
                        ToSlice(keys::PrefixEnd(keys::Tag::kLog, fleet)));
      if (absl::Status erased = Write(fleet, batch, synced_write_options_,
                                      "erase the moved ingest log of fleet");
          !erased.ok()) {
        return erased;
      }
      FLEETMEM_LOG(kInfo) << "fleet \"" << fleet << "\": moved " << entries
                          << " ingest log entries from RocksDB into " << path_
                          << "/ingest-log";
    }
    return absl::OkStatus();
  }

  // Rewrites the table files of the fleet's records of `tags` without the
  // versions and tombstones they hide, so that their space returns now. A
  // failure is logged: the space returns at a later compaction.
  void CompactRanges(std::string_view fleet_id,
                     std::span<const keys::Tag> tags) {
    rocksdb::CompactRangeOptions compact;
    compact.bottommost_level_compaction =
        rocksdb::BottommostLevelCompaction::kForceOptimized;
    for (keys::Tag tag : tags) {
      const std::string begin = keys::Prefix(tag, fleet_id);
      const std::string end = keys::PrefixEnd(tag, fleet_id);
      const rocksdb::Slice from = ToSlice(begin);
      const rocksdb::Slice to = ToSlice(end);
      const rocksdb::Status compacted = db_->CompactRange(compact, &from, &to);
      if (!compacted.ok()) {
        FLEETMEM_LOG(kWarning)
            << "fleet \"" << fleet_id << "\": compacting "
            << keys::Describe(begin)
            << " failed (its space returns at a later compaction): "
            << compacted.ToString();
      }
    }
  }

  // The fleets that have records of `tag`, ascending.
  absl::StatusOr<std::vector<std::string>> FleetsWith(keys::Tag tag) {
    std::vector<std::string> fleets;
    absl::Status listed = ForEachFleet(
        tag, [&](std::string_view fleet_id) { fleets.emplace_back(fleet_id); });
    if (!listed.ok()) return listed;
    return fleets;
  }

  // Calls `visit` with each fleet that has records of `tag`, ascending: a
  // skip scan, one seek per fleet, not one step per record.
  absl::Status ForEachFleet(keys::Tag tag,
                            absl::FunctionRef<void(std::string_view)> visit) {
    const char first = static_cast<char>(tag);
    std::unique_ptr<rocksdb::Iterator> it(
        db_->NewIterator(rocksdb::ReadOptions()));
    it->Seek(ToSlice(std::string(1, first)));
    while (it->Valid() && it->key().size() > 0 && it->key()[0] == first) {
      const std::optional<keys::ParsedKey> parsed =
          keys::Parse(ToView(it->key()));
      if (!parsed) {
        return absl::DataLossError(
            absl::StrCat("malformed key in RocksDB at ", path_, ": ",
                         keys::Describe(ToView(it->key()))));
      }
      const std::string fleet_id(parsed->fleet_id);
      visit(fleet_id);
      it->Seek(ToSlice(keys::PrefixEnd(tag, fleet_id)));
    }
    return FromRocksDb(it->status(), "list fleets");
  }

  // Fills the code of each trace in `traces` that has none (its record is
  // of layout 2) and that `code_held_elsewhere` (if set) does not claim,
  // from its key under keys::CodeKey. One iterator, in key order: it steps
  // to the next code when that is the one needed (a load without an index
  // snapshot reads them all) and seeks over a run of codes held elsewhere
  // (a load with one reads a few). DATA_LOSS naming the trace if its code
  // is missing.
  absl::Status ReadCodes(
      const rocksdb::ReadOptions& read, std::string_view fleet_id,
      const std::function<bool(const TraceKey&)>& code_held_elsewhere,
      TraceTable& traces, size_t* codes_read) {
    const std::string end = keys::PrefixEnd(keys::Tag::kCode, fleet_id);
    const rocksdb::Slice upper_bound = ToSlice(end);
    rocksdb::ReadOptions options = read;
    options.iterate_upper_bound = &upper_bound;
    std::unique_ptr<rocksdb::Iterator> it(db_->NewIterator(options));
    // Steps before a seek: a seek costs a few steps' worth of reading.
    constexpr int kStepsBeforeSeek = 4;
    absl::Status status = traces.ForEach([&](core::MemoryTrace& trace) {
      if (!trace.code.empty()) return absl::OkStatus();  // layout 1
      if (code_held_elsewhere && code_held_elsewhere(trace.key())) {
        return absl::OkStatus();
      }
      const std::string key = keys::CodeKey(fleet_id, trace.key());
      const rocksdb::Slice wanted = ToSlice(key);
      for (int step = 0; step < kStepsBeforeSeek && it->Valid() &&
                         it->key().compare(wanted) < 0;
           ++step) {
        it->Next();
      }
      if (!it->Valid() || it->key().compare(wanted) < 0) it->Seek(wanted);
      if (!it->status().ok()) return FromRocksDb(it->status(), "read codes");
      if (!it->Valid() || it->key() != wanted) {
        return absl::DataLossError(absl::StrCat(
            "corrupt store: ",
            keys::Describe(keys::TraceKey(fleet_id, trace.key())),
            " has no code (", keys::Describe(key), " is missing)"));
      }
      absl::Status decoded = DecodeCode(key, ToView(it->value()), &trace.code);
      ++*codes_read;
      it->Next();
      return decoded;
    });
    if (!status.ok()) return status;
    return FromRocksDb(it->status(), "read codes");
  }

  // Index snapshots live beside RocksDB's files, one per fleet.
  std::string SnapshotDirectory() const { return path_ + "/index-snapshots"; }

  template <typename T>
  static absl::Status Append(absl::StatusOr<T> value, std::vector<T>* out) {
    if (!value.ok()) return value.status();
    out->push_back(std::move(*value));
    return absl::OkStatus();
  }

  // Visits every record of (tag, fleet), ascending by key.
  absl::Status Scan(
      const rocksdb::ReadOptions& read, keys::Tag tag,
      std::string_view fleet_id,
      absl::FunctionRef<absl::Status(std::string_view, std::string_view)>
          visit) {
    return ForEachInRange(db_.get(), read, keys::Prefix(tag, fleet_id),
                          keys::PrefixEnd(tag, fleet_id),
                          [&](std::string_view key,
                              std::string_view value) -> absl::StatusOr<bool> {
                            if (absl::Status status = visit(key, value);
                                !status.ok()) {
                              return status;
                            }
                            return true;
                          });
  }

  // Writes `batch` of the fleet: refused without room (CheckRoom); a
  // failed write waits for RocksDB to resume and is retried (a batch
  // applied twice leaves the same state). `what` names it in the error.
  absl::Status Write(std::string_view fleet_id, rocksdb::WriteBatch& batch,
                     const rocksdb::WriteOptions& options,
                     std::string_view what) {
    // The fleet's index snapshot no longer describes it: its mark goes in
    // the same batch (no mark is put meanwhile).
    std::optional<SnapshotFileId> mark;
    absl::Status status;
    {
      absl::ReaderMutexLock lock(&marks_mu_);
      auto it = marks_.find(fleet_id);
      if (it != marks_.end()) mark = it->second;
      if (mark) batch.Delete(ToSlice(keys::SnapshotMarkKey(fleet_id)));
      status = WriteBatchOf(fleet_id, batch, options, what);
    }
    if (status.ok() && mark) {
      // Unless a newer mark was put since (another snapshot's).
      absl::MutexLock lock(&marks_mu_);
      auto it = marks_.find(fleet_id);
      if (it != marks_.end() && it->second == *mark) marks_.erase(it);
    }
    return status;
  }

  // Write without the mark's deletion.
  absl::Status WriteBatchOf(std::string_view fleet_id,
                            rocksdb::WriteBatch& batch,
                            const rocksdb::WriteOptions& options,
                            std::string_view what) {
    // The batch goes to the write-ahead log now and to a table file later.
    if (absl::Status room = CheckRoom(fleet_id, 2 * batch.GetDataSize());
        !room.ok()) {
      return room;
    }
    if (absl::Status resumed = ResumeAfterError(); !resumed.ok()) {
      return resumed;
    }
    rocksdb::Status written = db_->Write(options, &batch);
    if (!written.ok()) {
      // A background error (e.g. a flush that met a disk someone else
      // filled) stops every write until RocksDB has recovered, which its own
      // auto-resume retries every kResumeInterval. While there is room
      // (CheckRoom), wait for that or resume ourselves, and retry: a
      // WriteBatch applied twice leaves the same state, so a retry cannot
      // double anything.
      FLEETMEM_LOG(kWarning) << "RocksDB " << what << " " << fleet_id
                             << " failed: " << written.ToString()
                             << "; waiting for RocksDB to resume";
      write_failed_ = true;
      for (int attempt = 0; attempt < kResumeAttempts && !written.ok();
           ++attempt) {
        absl::SleepFor(kResumeInterval);
        if (!CheckRoom(fleet_id, 2 * batch.GetDataSize()).ok()) break;
        if (!ResumeAfterError().ok()) continue;  // busy: auto-resume running
        written = db_->Write(options, &batch);
      }
    }
    if (!written.ok()) {
      write_failed_ = true;
      FLEETMEM_LOG(kError) << "RocksDB " << what << " " << fleet_id
                           << " failed: " << written.ToString();
    }
    return FromRocksDb(written, absl::StrCat(V(what), " ", V(fleet_id),
                                             " (nothing of it was stored)"));
  }

  // RESOURCE_EXHAUSTED if writing `bytes` would leave less than the
  // reserve free.
  absl::Status CheckRoom(std::string_view fleet_id, uint64_t bytes) {
    if (min_free_bytes_ == 0) return absl::OkStatus();
    absl::StatusOr<uint64_t> free = free_bytes_(path_);
    if (!free.ok()) return free.status();
    absl::MutexLock reserve(&reserve_mu_);
    const uint64_t needed = min_free_bytes_ + bytes;
    if (*free >= needed) {
      // The reserve file comes on top of min_free_bytes: RocksDB's flushes
      // need all of that while serving (with half of it, a flush met a full
      // disk and RocksDB aborted).
      TakeReserve(*free - bytes);
      if (low_space_) {
        FLEETMEM_LOG(kInfo) << "disk space is back under " << path_ << " ("
                            << *free << " bytes free); writes resume";
        low_space_ = false;
      }
      return absl::OkStatus();
    }
    // The ingest log's spare segments (kept so that a segment's appends
    // overwrite rather than grow a file) go first when space is short.
    if (log_ != nullptr && log_->DropSpares() > 0) {
      absl::StatusOr<uint64_t> after = free_bytes_(path_);
      if (after.ok() && *after >= needed) return absl::OkStatus();
    }
    if (!low_space_) {
      FLEETMEM_LOG(kError) << "disk nearly full under " << path_ << ": "
                           << *free << " bytes free, reserve "
                           << min_free_bytes_ << "; refusing writes";
      low_space_ = true;
    }
    return absl::ResourceExhaustedError(absl::StrCat(
        "disk nearly full: ", *free, " bytes free under ", path_,
        ", a write of fleet ", V(fleet_id), " needs ", bytes,
        " above the reserve of ", min_free_bytes_,
        " (storage.min_free_bytes); nothing was stored. Reads are served; "
        "writes resume once space is freed"));
  }

  // Creates the reserve file if it is not held and `free` bytes leave room
  // for it above min_free_bytes.
  void TakeReserve(uint64_t free) ABSL_EXCLUSIVE_LOCKS_REQUIRED(reserve_mu_) {
    if (reserve_given_back_->exchange(false)) reserve_held_ = false;
    if (!reserve_held_ && reserve_bytes_ > 0 &&
        free >= min_free_bytes_ + reserve_bytes_) {
      reserve_held_ = CreateReserve(ReservePath(path_), reserve_bytes_);
    }
  }

  // After a failed write RocksDB may hold a background error that stops
  // every later write; ask it to resume (it re-checks the files).
  absl::Status ResumeAfterError() {
    if (!write_failed_) return absl::OkStatus();
    const rocksdb::Status resumed = db_->Resume();
    if (!resumed.ok()) {
      return FromRocksDb(resumed,
                         "resume after a failed write (nothing was stored)");
    }
    FLEETMEM_LOG(kInfo) << "RocksDB at " << path_
                        << " resumed after a failed write";
    write_failed_ = false;
    return absl::OkStatus();
  }

  // Outlives db_ (declared first, destroyed last).
  const std::unique_ptr<rocksdb::Env> env_;
  const std::shared_ptr<std::atomic<bool>> reserve_given_back_;
  std::unique_ptr<rocksdb::DB> db_;
  std::unique_ptr<SegmentLog> log_;
  const std::string path_;
  const uint64_t min_free_bytes_;
  const std::function<absl::StatusOr<uint64_t>(const std::string&)> free_bytes_;
  rocksdb::WriteOptions write_options_;
  rocksdb::WriteOptions synced_write_options_;
  rocksdb::WriteOptions unsynced_write_options_;
  absl::Mutex apply_mu_;
  // Held shared by every write of a fleet's state (across the write, so
  // that no mark is put meanwhile), alone to change marks_.
  absl::Mutex marks_mu_;
  // The marks in the store (keys.h: 's'), by fleet.
  std::map<std::string, SnapshotFileId, std::less<>> marks_
      ABSL_GUARDED_BY(marks_mu_);
  // Written by Apply (under apply_mu_) and by the log's appends and trims
  // (not under it).
  std::atomic<bool> low_space_ = false;
  const uint64_t reserve_bytes_;  // 0: no reserve file
  absl::Mutex reserve_mu_;
  bool reserve_held_ ABSL_GUARDED_BY(reserve_mu_);
  std::atomic<bool> write_failed_ = false;
};

rocksdb::Options MakeOptions(const RocksDbStoreOptions& options,
                             rocksdb::Env* env) {
  rocksdb::Options db_options;
  db_options.env = env;
  db_options.create_if_missing = options.create_if_missing;
  db_options.max_background_jobs = std::max(1, options.background_jobs);
  db_options.write_buffer_size = options.write_buffer_bytes;
  // RocksDB's info log goes to the server's log, not to a LOG file beside
  // the data: a LOG write that met a full disk aborted the server
  // (rocksdb_info_log.h).
  db_options.info_log = NewRocksDbInfoLog();
  if (options.compress) {
    const std::vector<rocksdb::CompressionType> supported =
        rocksdb::GetSupportedCompressions();
    auto has = [&](rocksdb::CompressionType type) {
      return std::find(supported.begin(), supported.end(), type) !=
             supported.end();
    };
    if (has(rocksdb::kLZ4Compression)) {
      db_options.compression = rocksdb::kLZ4Compression;
    } else if (has(rocksdb::kSnappyCompression)) {
      db_options.compression = rocksdb::kSnappyCompression;
    }
    if (has(rocksdb::kZSTD)) {
      db_options.bottommost_compression = rocksdb::kZSTD;
    }
  } else {
    db_options.compression = rocksdb::kNoCompression;
  }
  rocksdb::BlockBasedTableOptions table;
  if (options.block_cache_bytes > 0) {
    table.block_cache = rocksdb::NewLRUCache(options.block_cache_bytes);
  } else {
    table.no_block_cache = true;
  }
  if (options.bloom_bits_per_key > 0) {
    table.filter_policy.reset(
        rocksdb::NewBloomFilterPolicy(options.bloom_bits_per_key));
  }
  db_options.table_factory.reset(rocksdb::NewBlockBasedTableFactory(table));
  // After a retryable background error (I/O), RocksDB resumes by itself;
  // retry every 200 ms instead of every second.
  db_options.bgerror_resume_retry_interval =
      absl::ToInt64Microseconds(kResumeInterval);
  // Recovery from a no-space background error needs an SstFileManager (it
  // watches the free space and resumes the database); it also makes RocksDB
  // check the free space before a compaction.
  db_options.sst_file_manager.reset(rocksdb::NewSstFileManager(env));
  return db_options;
}

// Writes the layout version into a new database; refuses another version.
// The store's key layout: the current one for a new store (written now),
// keys::kFormatVersion1 for one to migrate, FAILED_PRECONDITION for any
// other.
absl::StatusOr<std::string> CheckFormat(rocksdb::DB* db,
                                        const std::string& path) {
  std::string version;
  const rocksdb::Status got =
      db->Get(rocksdb::ReadOptions(), ToSlice(keys::kFormatKey), &version);
  if (got.IsNotFound()) {
    absl::Status written = WriteFormat(db, path);
    if (!written.ok()) return written;
    return std::string(keys::kFormatVersion);
  }
  if (!got.ok()) {
    return FromRocksDb(got,
                       absl::StrCat("read format version at '", path, "'"));
  }
  if (version != keys::kFormatVersion && version != keys::kFormatVersion1) {
    return absl::FailedPreconditionError(
        absl::StrCat("RocksDB at '", path, "' has key layout \"", version,
                     "\", this build reads \"", V(keys::kFormatVersion),
                     "\" (and migrates \"", V(keys::kFormatVersion1), "\")"));
  }
  return version;
}

absl::StatusOr<std::unique_ptr<RocksDbStore>> Open(
    const RocksDbStoreOptions& options) {
  if (options.path.empty()) {
    return absl::InvalidArgumentError("RocksDbStoreOptions.path is empty");
  }
  if (options.create_if_missing) {
    std::error_code error;
    std::filesystem::create_directories(options.path, error);
    if (error) {
      return absl::UnavailableError(
          absl::StrCat("cannot create RocksDB directory '", options.path,
                       "': ", error.message()));
    }
  }
  // On a nearly full filesystem the reserve file goes first: opening writes
  // (a new write-ahead log, the manifest, a flush of the recovered one).
  const std::string reserve = ReservePath(options.path);
  if (!options.free_bytes && options.min_free_bytes > 0 &&
      HasReserve(reserve)) {
    absl::StatusOr<uint64_t> free = StatvfsFreeBytes(options.path);
    if (!free.ok() || *free < options.min_free_bytes) {
      unlink(reserve.c_str());
      FLEETMEM_LOG(kWarning)
          << "disk nearly full under " << options.path
          << (free.ok() ? absl::StrCat(" (", *free, " bytes free)") : "")
          << ": reserve file given back so that the store can open; writes "
             "are refused until space is freed";
    }
  }
  // Without the reserve file (none was ever made: the filesystem was short
  // at every open and write), an open on a filesystem with less than the
  // reserve file's size free is refused here: RocksDB's open writes, and
  // Debian's build aborts on a failed write-ahead-log write.
  if (!options.free_bytes && options.min_free_bytes > 0) {
    absl::StatusOr<uint64_t> free = StatvfsFreeBytes(options.path);
    const uint64_t needed = options.min_free_bytes / 2;
    if (free.ok() && *free < needed) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "disk nearly full: ", *free, " bytes free under ", options.path,
          "; opening the store needs ", needed,
          " (half of storage.min_free_bytes) and it has no reserve file left "
          "to give back; nothing was opened or changed. Free space and "
          "start again"));
    }
  }
  auto reserve_given_back = std::make_shared<std::atomic<bool>>(false);
  std::unique_ptr<rocksdb::Env> env = MakeEnv(options.path, reserve_given_back);
  rocksdb::DB* raw = nullptr;
  const rocksdb::Status status =
      rocksdb::DB::Open(MakeOptions(options, env.get()), options.path, &raw);
  if (!status.ok()) {
    delete raw;
    return FromRocksDb(status, absl::StrCat("open '", options.path, "'"));
  }
  std::unique_ptr<rocksdb::DB> db(raw);
  absl::StatusOr<std::string> format = CheckFormat(db.get(), options.path);
  if (!format.ok()) {
    db->Close().PermitUncheckedError();
    return format.status();
  }
  FLEETMEM_LOG(kInfo) << "opened RocksDB store at " << options.path
                      << (options.sync ? " (sync writes)" : " (async writes)");
  auto store = std::make_unique<RocksDbStore>(
      std::move(env), std::move(reserve_given_back), std::move(db), options);
  if (absl::Status log = store->OpenMarksAndLog(); !log.ok()) return log;
  store->TakeReserveAtOpen();
  if (*format == keys::kFormatVersion1) {
    if (absl::Status migrated = store->MigrateCodes(); !migrated.ok()) {
      return absl::Status(
          migrated.code(),
          absl::StrCat("migrating RocksDB at '", options.path, "' to \"",
                       V(keys::kFormatVersion), "\": ", migrated.message(),
                       " (the store stays readable by this build; the "
                       "migration resumes at the next start)"));
    }
  }
  return store;
}

}  // namespace

absl::StatusOr<LocalStorage> OpenLocalStorage(
    const RocksDbStoreOptions& options) {
  try {
    absl::StatusOr<std::unique_ptr<RocksDbStore>> opened = Open(options);
    if (!opened.ok()) return opened.status();
    LocalStorage storage;
    storage.log = (*opened)->log();
    storage.store = *std::move(opened);
    return storage;
  } catch (const std::exception& e) {
    return absl::InternalError(
        absl::StrCat("opening RocksDB at '", options.path, "': ", e.what()));
  }
}

absl::StatusOr<std::unique_ptr<engine::MemoryStore>> OpenRocksDbStore(
    const RocksDbStoreOptions& options) {
  absl::StatusOr<LocalStorage> opened = OpenLocalStorage(options);
  if (!opened.ok()) return opened.status();
  return std::move(opened->store);
}

}  // namespace fleetmem::storage
