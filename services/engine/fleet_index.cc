#include "services/engine/fleet_index.h"

#include <algorithm>
#include <string>
#include <string_view>
#include <system_error>
#include <thread>
#include <utility>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"

namespace fleetmem::engine {
namespace {

// Stored traces whose codes a reconciled snapshot must hold as the store
// does (a sample: a trace's code never changes under its key, so a
// difference means the snapshot is of another history of the fleet).
constexpr size_t kCodesCheckedOnLoad = 1024;
// ... taken as runs of this many consecutive handles: traces are mostly
// indexed in key order (a robot's segment at a time), so a run's codes lie
// side by side in the store and a cold restart reads a few blocks per run
// instead of seeking for each code (1,024 seeks took 7 s at 10,000,000).
constexpr size_t kCheckedRun = 32;

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

// A sample of the snapshot's `kept` traces that came with a code, spread
// over all of them, must have the codes the store has: DATA_LOSS naming
// the first that does not.
absl::Status CheckSnapshotCodes(
    const PlaceIndex& loaded, const TraceHandles& saved,
    std::span<const core::MemoryTrace* const> kept) {
  std::vector<const core::MemoryTrace*> with_code;
  for (const core::MemoryTrace* trace : kept) {
    if (!trace->code.empty()) with_code.push_back(trace);
  }
  std::vector<float> code;
  const size_t step =
      std::max<size_t>(1, with_code.size() / kCodesCheckedOnLoad);
  for (size_t i = 0; i < with_code.size(); i += step) {
    const core::MemoryTrace& trace = *with_code[i];
    if (!loaded.CopyCode(saved.Find(trace.key()), &code) ||
        code != trace.code) {
      return absl::DataLossError(
          absl::StrCat("the snapshot's code of trace (\"", trace.robot_id,
                       "\", ", trace.seq, ") differs from the store's"));
    }
  }
  return absl::OkStatus();
}

// The snapshot's handles of traces the store no longer holds (forgotten or
// downsampled since the snapshot).
std::vector<uint64_t> GoneHandles(
    const TraceHandles& saved,
    const std::vector<const core::MemoryTrace*>& traces) {
  absl::flat_hash_set<core::TraceKey> stored;
  stored.reserve(traces.size());
  for (const core::MemoryTrace* trace : traces) stored.insert(trace->key());
  std::vector<uint64_t> gone;
  saved.ForEach([&](uint64_t handle, std::string_view robot_id, uint64_t seq) {
    if (!stored.contains(core::TraceKey{std::string(robot_id), seq})) {
      gone.push_back(handle);
    }
  });
  return gone;
}

}  // namespace

bool FleetIndex::CheckedOnLoad(uint64_t handle, size_t saved) {
  const size_t runs = kCodesCheckedOnLoad / kCheckedRun;
  return handle % std::max<size_t>(kCheckedRun, saved / runs) < kCheckedRun;
}

void FleetIndex::Reset() {
  index_.reset();
  handles_.Clear();
  next_handle_ = 1;
  changes_ = 0;
  snapshot_at_.reset();
}

void FleetIndex::Start(std::unique_ptr<PlaceIndex> index) {
  index_ = std::move(index);
  handles_.Clear();
  next_handle_ = 1;
  if (index_ != nullptr && deferred_until_ > absl::Now()) {
    index_->DeferIndexing(deferred_until_);
  }
}

void FleetIndex::DeferIndexing(absl::Time until) {
  deferred_until_ = until;
  if (index_ != nullptr) index_->DeferIndexing(until);
}

absl::Status FleetIndex::Add(
    const std::vector<const core::MemoryTrace*>& traces,
    const std::function<void()>& meanwhile) {
  if (traces.empty()) {
    if (meanwhile) meanwhile();
    return absl::OkStatus();
  }
  if (index_ == nullptr) return absl::InternalError("the fleet has no index");
  std::vector<uint64_t> ids;
  std::vector<std::span<const float>> codes;
  ids.reserve(traces.size());
  codes.reserve(traces.size());
  for (const core::MemoryTrace* trace : traces) {
    ids.push_back(next_handle_++);
    codes.push_back(trace->code);
  }
  absl::Status status;
  RunBeside(meanwhile, traces.size(),
            [&] { status = index_->AddNormalizedUnthrottled(ids, codes); });
  ++changes_;
  if (!status.ok()) return status;
  handles_.Reserve(handles_.size() + traces.size());
  for (size_t i = 0; i < traces.size(); ++i) {
    handles_.Assign(traces[i]->key(), ids[i]);
  }
  return absl::OkStatus();
}

absl::Status FleetIndex::Remove(const std::vector<core::TraceKey>& keys) {
  std::vector<uint64_t> ids;
  for (const core::TraceKey& key : keys) {
    const uint64_t handle = handles_.Erase(key);
    if (handle != 0) ids.push_back(handle);
  }
  if (ids.empty() || index_ == nullptr) return absl::OkStatus();
  ++changes_;
  return index_->Remove(ids);
}

bool FleetIndex::CopyCode(const core::TraceKey& key,
                          std::vector<float>* code) const {
  const uint64_t handle = handles_.Find(key);
  return handle != 0 && index_ != nullptr && index_->CopyCode(handle, code);
}

bool FleetIndex::CopyCodes(std::span<const core::TraceKey* const> keys,
                           std::span<std::vector<float>* const> codes) const {
  if (index_ == nullptr) return keys.empty();
  std::vector<uint64_t> ids;
  ids.reserve(keys.size());
  for (const core::TraceKey* key : keys) ids.push_back(handles_.Find(*key));
  return index_->CopyCodes(ids, codes);
}

std::vector<bool> FleetIndex::HoldsCodes(
    std::span<const core::TraceKey* const> keys) const {
  std::vector<bool> held(keys.size(), false);
  if (index_ == nullptr) return held;
  std::vector<uint64_t> ids;
  std::vector<size_t> at;
  for (size_t i = 0; i < keys.size(); ++i) {
    const uint64_t handle = handles_.Find(*keys[i]);
    if (handle == 0) continue;
    ids.push_back(handle);
    at.push_back(i);
  }
  const std::vector<bool> holds = index_->HoldsCodes(ids);
  for (size_t j = 0; j < at.size(); ++j) held[at[j]] = holds[j];
  return held;
}

void FleetIndex::SaveHandles(core::ByteWriter& out) const {
  out.Put<uint64_t>(next_handle_);
  handles_.Save(out);
}

absl::Status FleetIndex::SaveIndex(core::ByteWriter& out) const {
  if (index_ == nullptr) return absl::InternalError("the fleet has no index");
  return index_->Save(out);
}

absl::StatusOr<FleetIndex::Reconciled> FleetIndex::Reconcile(
    std::unique_ptr<PlaceIndex> loaded, TraceHandles saved,
    uint64_t next_handle, const std::vector<const core::MemoryTrace*>& stored) {
  Reset();
  Reconciled counts;
  std::vector<const core::MemoryTrace*> missing;
  std::vector<const core::MemoryTrace*> kept;
  kept.reserve(std::min(stored.size(), saved.size()));
  for (const core::MemoryTrace* trace : stored) {
    // A trace without its code is one the load left to the snapshot after
    // finding it in `saved`: not looked up again (10,000,000 lookups were
    // 7 s of a restart).
    const bool held = trace->code.empty() || saved.contains(trace->key());
    (held ? kept : missing).push_back(trace);
  }
  if (kept.size() > saved.size()) {
    return absl::DataLossError(
        absl::StrCat(kept.size(),
                     " stored traces came without codes or are "
                     "in the snapshot, which holds only ",
                     saved.size()));
  }
  absl::Status status = CheckSnapshotCodes(*loaded, saved, kept);
  if (!status.ok()) return status;
  const std::vector<uint64_t> gone = kept.size() < saved.size()
                                         ? GoneHandles(saved, stored)
                                         : std::vector<uint64_t>{};
  status = loaded->Remove(gone);
  if (!status.ok()) return status;
  for (uint64_t handle : gone) saved.EraseHandle(handle);
  index_ = std::move(loaded);
  handles_ = std::move(saved);
  next_handle_ = next_handle;
  status = Add(missing);
  changes_ = 0;
  if (!status.ok()) {
    Reset();
    return status;
  }
  counts.kept = kept.size();
  counts.added = missing.size();
  counts.removed = gone.size();
  return counts;
}

}  // namespace fleetmem::engine
