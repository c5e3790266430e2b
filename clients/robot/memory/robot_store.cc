#include "clients/robot/memory/robot_store.h"

#include <sys/statvfs.h>

#include <filesystem>
#include <system_error>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "rocksdb/db.h"
#include "rocksdb/options.h"
#include "rocksdb/write_batch.h"

namespace fleetmem::robot {
namespace {

constexpr char kStateKey[] = "m/state";
constexpr char kOpenPrefix[] = "o/";
constexpr char kQueuePrefix[] = "q/";
// seq -> source index of every sealed trace (8 bytes each), kept after the
// upload: what an encoder migration re-encodes (RobotStore::SourceIndices).
constexpr char kSourcePrefix[] = "i/";

// Prefix + big-endian number, so keys sort by number.
std::string Key(const char* prefix, uint64_t number) {
  std::string key(prefix);
  for (int shift = 56; shift >= 0; shift -= 8) {
    key.push_back(static_cast<char>((number >> shift) & 0xff));
  }
  return key;
}

uint64_t KeyNumber(const rocksdb::Slice& key) {
  uint64_t number = 0;
  for (size_t i = key.size() - 8; i < key.size(); ++i) {
    number = (number << 8) | static_cast<unsigned char>(key[i]);
  }
  return number;
}

absl::Status FromRocks(const rocksdb::Status& status, std::string_view what) {
  if (status.ok()) return absl::OkStatus();
  const std::string message =
      absl::StrCat(std::string(what), ": ", status.ToString());
  if (status.IsNoSpace() || status.IsIOError() || status.IsBusy() ||
      status.IsTimedOut() || status.IsTryAgain()) {
    return absl::UnavailableError(message);
  }
  return absl::InternalError(message);
}

int64_t NowUnixNs() { return absl::ToUnixNanos(absl::Now()); }

}  // namespace

namespace {

core::FirstCorrectRanks RanksOf(
    const google::protobuf::RepeatedField<uint64_t>& histogram) {
  core::FirstCorrectRanks ranks;
  for (int r = 0; r < histogram.size(); ++r) {
    ranks.insert(ranks.end(), histogram[r], r);
  }
  return ranks;
}

}  // namespace

core::FirstCorrectRanks RelocalisationRanks(const RobotState& state) {
  return RanksOf(state.relocalisation_ranks());
}

core::FirstCorrectRanks SequenceRanks(const RobotState& state) {
  return RanksOf(state.sequence_ranks());
}

const char* FullPolicyName(FullPolicy policy) {
  return policy == FullPolicy::kRefuse ? "refuse" : "drop-oldest";
}

absl::StatusOr<FullPolicy> ParseFullPolicy(std::string_view name) {
  if (name == "refuse") return FullPolicy::kRefuse;
  if (name == "drop-oldest") return FullPolicy::kDropOldest;
  return absl::InvalidArgumentError(
      absl::StrCat("queue full policy \"", std::string(name),
                   "\" must be refuse or drop-oldest"));
}

RobotStore::RobotStore(std::unique_ptr<rocksdb::DB> db,
                       RobotStoreOptions options)
    : db_(std::move(db)), options_(options) {}

RobotStore::~RobotStore() = default;

absl::StatusOr<std::unique_ptr<RobotStore>> RobotStore::Open(
    const std::string& dir, const RobotIdentity& identity,
    const RobotStoreOptions& options) {
  std::error_code error;
  std::filesystem::create_directories(dir, error);
  if (error) {
    return absl::UnavailableError(
        absl::StrCat("cannot create ", dir, ": ", error.message()));
  }
  rocksdb::Options db_options;
  db_options.create_if_missing = true;
  db_options.max_open_files = 64;
  db_options.keep_log_file_num = 2;
  // A robot's queue is small and its disk may be too: a 4 MiB memtable
  // (about 2,000 HOG traces) keeps the write-ahead log and its
  // preallocation small.
  db_options.write_buffer_size = 4u << 20;
  rocksdb::DB* raw = nullptr;
  const std::string path = (std::filesystem::path(dir) / "queue").string();
  absl::Status opened =
      FromRocks(rocksdb::DB::Open(db_options, path, &raw),
                absl::StrCat("cannot open the robot store ", path));
  if (!opened.ok()) return opened;
  std::unique_ptr<RobotStore> store(
      new RobotStore(std::unique_ptr<rocksdb::DB>(raw), options));
  store->path_ = path;
  absl::Status loaded = store->Load();
  if (!loaded.ok()) return loaded;
  absl::MutexLock lock(&store->mu_);
  RobotState& state = store->state_;
  if (state.robot_id().empty()) {
    store->created_ = true;
    RobotState fresh;
    fresh.set_robot_id(identity.robot_id);
    fresh.set_fleet_id(identity.fleet_id);
    fresh.set_source(identity.source);
    fresh.set_next_seq(1);
    rocksdb::WriteBatch batch;
    absl::Status committed = store->Commit(batch, fresh);
    if (!committed.ok()) return committed;
    return store;
  }
  if (state.robot_id() != identity.robot_id ||
      state.fleet_id() != identity.fleet_id ||
      state.source() != identity.source) {
    return absl::FailedPreconditionError(absl::StrCat(
        dir, " holds the state of robot \"", state.robot_id(), "\" of fleet \"",
        state.fleet_id(), "\" reading ", state.source(), "; this is robot \"",
        identity.robot_id, "\" of fleet \"", identity.fleet_id, "\" reading ",
        identity.source, ". Use another --data-dir (its queue still holds ",
        store->queue_.size(), " traces)"));
  }
  return store;
}

absl::Status RobotStore::Load() {
  absl::MutexLock lock(&mu_);
  std::string value;
  const rocksdb::Status got =
      db_->Get(rocksdb::ReadOptions(), kStateKey, &value);
  if (got.ok()) {
    if (!state_.ParseFromString(value)) {
      return absl::DataLossError("the robot store's state does not parse");
    }
  } else if (!got.IsNotFound()) {
    return FromRocks(got, "cannot read the robot store's state");
  }
  std::unique_ptr<rocksdb::Iterator> it(
      db_->NewIterator(rocksdb::ReadOptions()));
  for (it->Seek(kOpenPrefix); it->Valid() && it->key().starts_with(kOpenPrefix);
       it->Next()) {
    open_[KeyNumber(it->key())] = it->value().size();
    bytes_ += it->value().size();
  }
  for (it->Seek(kQueuePrefix);
       it->Valid() && it->key().starts_with(kQueuePrefix); it->Next()) {
    StoredTrace stored;
    if (!stored.ParseFromArray(it->value().data(),
                               static_cast<int>(it->value().size()))) {
      return absl::DataLossError(absl::StrCat(
          "queued trace seq ", KeyNumber(it->key()), " does not parse"));
    }
    queue_[KeyNumber(it->key())] = {it->value().size(),
                                    stored.stored_unix_ns()};
    bytes_ += it->value().size();
  }
  return FromRocks(it->status(), "cannot read the robot store");
}

absl::Status RobotStore::CheckReserve(uint64_t bytes,
                                      std::string_view what) const {
  if (options_.min_free_bytes == 0) return absl::OkStatus();
  uint64_t free = 0;
  if (options_.free_bytes) {
    free = options_.free_bytes();
  } else {
    struct statvfs info;
    if (statvfs(path_.c_str(), &info) != 0) return absl::OkStatus();
    free = static_cast<uint64_t>(info.f_bavail) * info.f_frsize;
  }
  // Twice the payload: the write-ahead log and the memtable's later flush.
  if (free >= options_.min_free_bytes + 2 * bytes) return absl::OkStatus();
  return absl::UnavailableError(absl::StrCat(
      "disk nearly full: ", free, " bytes free under ", path_,
      ", below the reserve of ", options_.min_free_bytes,
      " bytes (--disk-reserve-mb); ", std::string(what),
      " was not recorded; everything recorded before is kept. Free space "
      "and restart: the robot resumes there"));
}

absl::Status RobotStore::Commit(rocksdb::WriteBatch& batch,
                                const RobotState& next) {
  batch.Put(kStateKey, next.SerializeAsString());
  rocksdb::WriteOptions write;
  write.sync = options_.sync;
  absl::Status status =
      FromRocks(db_->Write(write, &batch), "the robot store could not write");
  if (status.ok()) state_ = next;
  return status;
}

absl::Status RobotStore::SetFirstSeq(uint64_t first_seq) {
  absl::MutexLock lock(&mu_);
  if (state_.next_seq() != 1 || state_.traces_queued() != 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "the robot has already given seqs up to ", state_.next_seq() - 1));
  }
  RobotState next = state_;
  next.set_next_seq(std::max<uint64_t>(first_seq, 1));
  rocksdb::WriteBatch batch;
  return Commit(batch, next);
}

RobotState RobotStore::state() const {
  absl::MutexLock lock(&mu_);
  return state_;
}

QueueInfo RobotStore::queue() const {
  absl::MutexLock lock(&mu_);
  QueueInfo info;
  info.depth = queue_.size();
  info.bytes = bytes_;
  info.open_segment = open_.size();
  if (!queue_.empty()) {
    info.oldest_stored_unix_ns = queue_.begin()->second.stored_unix_ns;
  }
  return info;
}

absl::Status RobotStore::RecordObservation(
    uint64_t source_index, const v1::MemoryTrace& trace,
    const std::function<void(RobotState&)>& update) {
  StoredTrace stored;
  *stored.mutable_trace() = trace;
  stored.set_source_index(source_index);
  stored.set_stored_unix_ns(NowUnixNs());
  const std::string value = stored.SerializeAsString();
  absl::Status reserve =
      CheckReserve(value.size(), absl::StrCat("observation ", source_index));
  if (!reserve.ok()) return reserve;
  absl::MutexLock lock(&mu_);
  if (source_index != state_.next_index()) {
    return absl::FailedPreconditionError(
        absl::StrCat("observation ", source_index, " is not the next one (",
                     state_.next_index(), ")"));
  }
  if (options_.full_policy == FullPolicy::kRefuse &&
      bytes_ + value.size() > options_.max_bytes) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "upload queue full: ", bytes_, " of ", options_.max_bytes,
        " bytes held by ", queue_.size(), " queued traces and ", open_.size(),
        " open observations; observation ", source_index,
        " was not recorded (policy refuse: waiting for the queue to drain)"));
  }
  RobotState next = state_;
  next.set_next_index(source_index + 1);
  next.set_observations(next.observations() + 1);
  if (update) update(next);
  rocksdb::WriteBatch batch;
  batch.Put(Key(kOpenPrefix, source_index), value);
  absl::Status status = Commit(batch, next);
  if (!status.ok()) return status;
  open_[source_index] = value.size();
  bytes_ += value.size();
  return absl::OkStatus();
}

absl::StatusOr<std::vector<StoredTrace>> RobotStore::OpenSegment() const {
  absl::MutexLock lock(&mu_);
  std::vector<StoredTrace> segment;
  std::unique_ptr<rocksdb::Iterator> it(
      db_->NewIterator(rocksdb::ReadOptions()));
  for (it->Seek(kOpenPrefix); it->Valid() && it->key().starts_with(kOpenPrefix);
       it->Next()) {
    StoredTrace& stored = segment.emplace_back();
    if (!stored.ParseFromArray(it->value().data(),
                               static_cast<int>(it->value().size()))) {
      return absl::DataLossError(absl::StrCat(
          "open observation ", KeyNumber(it->key()), " does not parse"));
    }
  }
  absl::Status status = FromRocks(it->status(), "cannot read the open segment");
  if (!status.ok()) return status;
  return segment;
}

absl::StatusOr<uint64_t> RobotStore::SealSegment(
    std::vector<v1::MemoryTrace> traces,
    const std::function<void(RobotState&)>& update) {
  absl::MutexLock lock(&mu_);
  if (traces.size() != open_.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("sealing ", traces.size(),
                     " traces, but the open segment "
                     "holds ",
                     open_.size(), " observations"));
  }
  uint64_t payload = 0;
  for (const auto& [index, bytes] : open_) payload += bytes;
  absl::Status reserve = CheckReserve(
      payload, absl::StrCat("the segment of ", open_.size(), " observations"));
  if (!reserve.ok()) return reserve;
  RobotState next = state_;
  const uint64_t first_seq = next.next_seq();
  rocksdb::WriteBatch batch;
  std::vector<std::pair<uint64_t, Queued>> added;
  uint64_t added_bytes = 0;
  const int64_t now = NowUnixNs();
  auto index = open_.begin();
  for (v1::MemoryTrace& trace : traces) {
    trace.set_seq(next.next_seq());
    StoredTrace stored;
    *stored.mutable_trace() = std::move(trace);
    stored.set_source_index(index->first);
    stored.set_stored_unix_ns(now);
    const std::string value = stored.SerializeAsString();
    batch.Delete(Key(kOpenPrefix, index->first));
    batch.Put(Key(kQueuePrefix, next.next_seq()), value);
    batch.Put(Key(kSourcePrefix, next.next_seq()), Key("", index->first));
    added.push_back({next.next_seq(), {value.size(), now}});
    added_bytes += value.size();
    next.set_next_seq(next.next_seq() + 1);
    ++index;
  }
  // Drop-oldest: make room for the sealed traces.
  uint64_t bytes_after = bytes_ - payload + added_bytes;
  std::vector<uint64_t> dropped;
  if (options_.full_policy == FullPolicy::kDropOldest) {
    for (auto it = queue_.begin();
         it != queue_.end() && bytes_after > options_.max_bytes; ++it) {
      batch.Delete(Key(kQueuePrefix, it->first));
      bytes_after -= it->second.bytes;
      dropped.push_back(it->first);
    }
  }
  next.set_traces_queued(next.traces_queued() + traces.size());
  next.set_traces_dropped(next.traces_dropped() + dropped.size());
  next.set_segments(next.segments() + 1);
  if (update) update(next);
  absl::Status status = Commit(batch, next);
  if (!status.ok()) return status;
  open_.clear();
  for (uint64_t seq : dropped) queue_.erase(seq);
  for (const auto& [seq, queued] : added) queue_[seq] = queued;
  bytes_ = bytes_after;
  return first_seq;
}

absl::StatusOr<std::vector<v1::MemoryTrace>> RobotStore::PeekQueue(
    size_t max) const {
  std::vector<v1::MemoryTrace> traces;
  std::unique_ptr<rocksdb::Iterator> it(
      db_->NewIterator(rocksdb::ReadOptions()));
  for (it->Seek(kQueuePrefix);
       it->Valid() && it->key().starts_with(kQueuePrefix) &&
       traces.size() < max;
       it->Next()) {
    StoredTrace stored;
    if (!stored.ParseFromArray(it->value().data(),
                               static_cast<int>(it->value().size()))) {
      return absl::DataLossError(absl::StrCat(
          "queued trace seq ", KeyNumber(it->key()), " does not parse"));
    }
    traces.push_back(std::move(*stored.mutable_trace()));
  }
  absl::Status status = FromRocks(it->status(), "cannot read the queue");
  if (!status.ok()) return status;
  return traces;
}

absl::Status RobotStore::MarkUploaded(uint64_t through_seq, uint64_t accepted,
                                      uint64_t duplicates) {
  absl::MutexLock lock(&mu_);
  rocksdb::WriteBatch batch;
  uint64_t freed = 0;
  auto end = queue_.upper_bound(through_seq);
  for (auto it = queue_.begin(); it != end; ++it) {
    batch.Delete(Key(kQueuePrefix, it->first));
    freed += it->second.bytes;
  }
  RobotState next = state_;
  next.set_traces_uploaded(next.traces_uploaded() + accepted + duplicates);
  next.set_upload_duplicates(next.upload_duplicates() + duplicates);
  absl::Status status = Commit(batch, next);
  if (!status.ok()) return status;
  queue_.erase(queue_.begin(), end);
  bytes_ -= freed;
  return absl::OkStatus();
}

absl::StatusOr<std::vector<SourceIndex>> RobotStore::SourceIndices(
    uint64_t after_seq, size_t max) const {
  std::vector<SourceIndex> found;
  std::unique_ptr<rocksdb::Iterator> it(
      db_->NewIterator(rocksdb::ReadOptions()));
  for (it->Seek(Key(kSourcePrefix, after_seq + 1));
       it->Valid() && it->key().starts_with(kSourcePrefix) &&
       found.size() < max;
       it->Next()) {
    if (it->value().size() != 8) {
      return absl::DataLossError(absl::StrCat(
          "the source index of seq ", KeyNumber(it->key()), " does not parse"));
    }
    found.push_back({KeyNumber(it->key()), KeyNumber(it->value())});
  }
  absl::Status status =
      FromRocks(it->status(), "cannot read the source indices");
  if (!status.ok()) return status;
  return found;
}

absl::Status RobotStore::DiscardOpenSegment() {
  absl::MutexLock lock(&mu_);
  if (open_.empty()) return absl::OkStatus();
  rocksdb::WriteBatch batch;
  uint64_t freed = 0;
  for (const auto& [index, bytes] : open_) {
    batch.Delete(Key(kOpenPrefix, index));
    freed += bytes;
  }
  RobotState next = state_;
  next.set_next_index(open_.begin()->first);
  next.set_observations(next.observations() - open_.size());
  absl::Status status = Commit(batch, next);
  if (!status.ok()) return status;
  open_.clear();
  bytes_ -= freed;
  return absl::OkStatus();
}

absl::Status RobotStore::Update(
    const std::function<void(RobotState&)>& update) {
  absl::MutexLock lock(&mu_);
  RobotState next = state_;
  update(next);
  rocksdb::WriteBatch batch;
  return Commit(batch, next);
}

}  // namespace fleetmem::robot
