#include "services/index/hnsw_index.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <condition_variable>
#include <exception>
#include <functional>
#include <mutex>
#include <new>
#include <shared_mutex>
#include <system_error>
#include <thread>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "services/common/background_thread.h"
#include "services/common/log.h"
#include "services/core/feature_space.h"
#include "services/core/hnsw_graph.h"
#include "services/index/exact_index.h"
#include "services/index/float_file.h"
#include "services/index/index_input.h"

namespace fleetmem::index {
namespace {

using engine::Neighbor;
using engine::SearchParams;

// Sorts by (distance, id) and keeps the first k.
void KeepNearest(std::vector<Neighbor>& neighbors, size_t k) {
  auto closer = [](const Neighbor& a, const Neighbor& b) {
    return a.distance < b.distance || (a.distance == b.distance && a.id < b.id);
  };
  if (neighbors.size() > k) {
    std::partial_sort(neighbors.begin(), neighbors.begin() + k, neighbors.end(),
                      closer);
    neighbors.resize(k);
  } else {
    std::sort(neighbors.begin(), neighbors.end(), closer);
  }
}

// KeepNearest of two lists that may both hold an id (the tiered index while
// a step's vectors are linked into its graph: they are still in its tail),
// each id once, at its smaller distance.
void KeepNearestOnce(std::vector<Neighbor>& neighbors, size_t k) {
  KeepNearest(neighbors, neighbors.size());
  absl::flat_hash_set<uint64_t> seen;
  size_t kept = 0;
  for (size_t i = 0; i < neighbors.size() && kept < k; ++i) {
    if (seen.insert(neighbors[i].id).second) neighbors[kept++] = neighbors[i];
  }
  neighbors.resize(kept);
}

// Links the staged nodes of `staged` on up to `threads` threads: the
// caller's and threads - 1 started for the call (a thread start is small
// against a step's inserts, 0.3-1 ms each at 256-d). One thread links them in
// order, which builds the graph the same Adds would.
void LinkOnThreads(core::HnswGraph& graph,
                   const core::HnswGraph::Staged& staged, size_t threads) {
  const size_t count = staged.slots.size();
  std::atomic<size_t> next{staged.linked};
  std::mutex error_mu;
  std::exception_ptr error;
  const auto link = [&] {
    for (size_t i; (i = next.fetch_add(1)) < count;) {
      try {
        graph.Link(staged, i);
      } catch (...) {
        const std::lock_guard lock(error_mu);
        if (!error) error = std::current_exception();
      }
    }
  };
  std::vector<std::thread> helpers;
  const size_t pending = count - staged.linked;
  for (size_t t = 1; t < std::min(threads, pending); ++t) {
    try {
      helpers.emplace_back(link);
    } catch (const std::system_error&) {
      break;  // no thread to be had: fewer do the work
    }
  }
  link();
  for (std::thread& helper : helpers) helper.join();
  if (error) std::rethrow_exception(error);
}

class HnswIndex final : public engine::PlaceIndex {
 public:
  HnswIndex(size_t dimension, HnswIndexOptions options)
      : options_(options),
        graph_(std::make_unique<core::HnswGraph>(dimension,
                                                 GraphOptions(options))) {}

  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override {
    return AddScaled(ids, vectors,
                     [](size_t, std::span<const float>) { return 1.0f; });
  }
  // Keeps each code as given, with the scale that makes it unit length: one
  // copy serves both Search and CopyCode.
  absl::Status AddNormalized(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) override {
    return AddScaled(ids, codes, [](size_t, std::span<const float> code) {
      return core::UnitScale(code);
    });
  }
  // Adds each vectors[i] standing for scale(i, vectors[i]) times it.
  template <typename Vector>
  absl::Status AddScaled(
      std::span<const uint64_t> ids, std::span<const Vector> vectors,
      const std::function<float(size_t, std::span<const float>)>& scale) {
    absl::StatusOr<core::HnswGraph::Staged> staged =
        StageScaled(ids, vectors, scale);
    if (!staged.ok()) return staged.status();
    return LinkStaged(*staged, ids.size());
  }
  // AddScaled in two steps, so that searches go on while the new nodes are
  // linked (the tiered index): StageScaled checks the batch and stores its
  // vectors, found by CopyCode and a scan but not by the graph's search
  // yet; LinkStaged links them. Nothing else may change the index from one
  // to the end of the other; Search may run beside LinkStaged once
  // set_linking(true).
  template <typename Vector>
  absl::StatusOr<core::HnswGraph::Staged> StageScaled(
      std::span<const uint64_t> ids, std::span<const Vector> vectors,
      const std::function<float(size_t, std::span<const float>)>& scale);
  // RESOURCE_EXHAUSTED if StageScaled could store only staged.slots.size()
  // of the `asked` vectors (the others are not added).
  absl::Status LinkStaged(const core::HnswGraph::Staged& staged, size_t asked);
  // While true, Search walks the graph with HnswGraph::SearchBesideLinks.
  void set_linking(bool linking) { linking_ = linking; }
  absl::Status Remove(std::span<const uint64_t> ids) override;
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override;
  size_t size() const override { return slot_of_.size(); }
  size_t dimension() const override { return graph_->dimension(); }
  bool HoldsCode(uint64_t id) const override { return contains(id); }
  // CopyCodes of the one id.
  bool CopyCode(uint64_t id, std::vector<float>* code) const override {
    return CopyCodes(std::span<const uint64_t>(&id, 1),
                     std::span<std::vector<float>* const>(&code, 1));
  }
  // CopyCode of each held id, the graph's rows read in one batch
  // (HnswGraph::CopyVectors); the code of an id not held is left as it is.
  bool CopyCodes(std::span<const uint64_t> ids,
                 std::span<std::vector<float>* const> codes) const override;
  absl::Status Save(core::ByteWriter& out) const override;
  void SavedToFile() override { graph_->AdoptSavedFloats(); }
  absl::Status Load(core::ByteReader& in) override;
  bool Damaged() const override {
    return damaged_.load(std::memory_order_acquire);
  }
  bool contains(uint64_t id) const { return slot_of_.contains(id); }

  void set_ef_search(size_t ef) { graph_->set_ef_search(ef); }
  size_t graph_bytes() const { return graph_->MemoryBytes(); }

  // Calls visit(id, vector as given, its scale) for every stored vector.
  // May throw std::system_error (floats kept in a file that cannot be
  // read).
  void ForEach(const std::function<void(uint64_t, std::span<const float>,
                                        float)>& visit) const {
    std::vector<float> vector(dimension());
    for (const auto& [id, slot] : slot_of_) {
      const float scale = graph_->CopyVector(slot, vector.data());
      visit(id, vector, scale);
    }
  }

 private:
  // The status of a read of the codes' floats that failed with `e`:
  // DATA_LOSS when a row failed its checksum (read from a damaged index
  // snapshot's file; the store still holds the code), which marks the
  // index Damaged; INTERNAL otherwise (an I/O error).
  absl::Status FloatsNotRead(const std::system_error& e,
                             absl::string_view what) const {
    const std::string message =
        absl::StrCat("HNSW index: ", what, ": ", e.what());
    if (e.code() != std::errc::bad_message) {
      return absl::InternalError(message);
    }
    damaged_.store(true, std::memory_order_release);
    return absl::DataLossError(message);
  }
  // Every accepted vector's distance to `scale` times `query`, by scanning.
  std::vector<Neighbor> Scan(std::span<const float> query, float scale,
                             const SearchParams& params) const;

  static core::HnswGraphOptions GraphOptions(const HnswIndexOptions& options) {
    return {.m = options.m,
            .ef_construction = options.ef_construction,
            .ef_search = options.ef_search,
            .seed = options.seed,
            .repair_probability = options.repair_probability,
            .scaled = true,
            .int8 = options.codes == HnswIndexOptions::Codes::kInt8,
            .float_rows = options.floats_dir.empty()
                              ? core::FloatRowsMaker()
                              : FloatRowsInFiles(options.floats_dir)};
  }

  const HnswIndexOptions options_;
  std::unique_ptr<core::HnswGraph> graph_;
  bool linking_ = false;
  // Set by FloatsNotRead (any reader's thread).
  mutable std::atomic<bool> damaged_ = false;
  absl::flat_hash_map<uint64_t, uint32_t> slot_of_;  // id -> slot
  std::vector<uint64_t> id_of_;                      // slot -> id
};

template <typename Vector>
absl::StatusOr<core::HnswGraph::Staged> HnswIndex::StageScaled(
    std::span<const uint64_t> ids, std::span<const Vector> vectors,
    const std::function<float(size_t, std::span<const float>)>& scale) {
  if (absl::Status status =
          CheckAddBatch(dimension(), ids, vectors,
                        [this](uint64_t id) { return slot_of_.contains(id); });
      !status.ok()) {
    return status;
  }
  try {
    const size_t needed = slot_of_.size() + ids.size();
    graph_->Reserve(needed);
    slot_of_.reserve(needed);
    // Doubling: a reserve of exactly `needed` copied the whole table at
    // every step of a few codes, 80 MB a step at 10,000,000 held.
    ReserveGeometric(id_of_, needed);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("HNSW index: out of memory in Add");
  }
  std::vector<const float*> data(ids.size());
  std::vector<float> scales(ids.size());
  for (size_t i = 0; i < ids.size(); ++i) {
    const std::span<const float> vector(vectors[i]);
    data[i] = vector.data();
    scales[i] = scale(i, vector);
  }
  core::HnswGraph::Staged staged;
  try {
    staged = graph_->Stage(data, scales);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("HNSW index: out of memory in Add");
  } catch (const std::system_error& e) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "HNSW index: no room for the codes' floats (nothing added): ",
        e.what()));
  }
  for (size_t i = 0; i < staged.slots.size(); ++i) {
    const uint32_t slot = staged.slots[i];
    if (slot >= id_of_.size()) id_of_.resize(slot + 1);
    id_of_[slot] = ids[i];
    slot_of_.emplace(ids[i], slot);
  }
  return staged;
}

absl::Status HnswIndex::LinkStaged(const core::HnswGraph::Staged& staged,
                                   size_t asked) {
  LinkOnThreads(*graph_, staged, options_.insert_threads);
  if (!staged.complete) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "HNSW index: out of memory, or the codes' floats could not be "
        "written, in Add after ",
        staged.slots.size(), " of ", asked, " vectors"));
  }
  return absl::OkStatus();
}

absl::Status HnswIndex::Remove(std::span<const uint64_t> ids) {
  for (uint64_t id : ids) {
    auto it = slot_of_.find(id);
    if (it == slot_of_.end()) continue;
    graph_->Remove(it->second);
    slot_of_.erase(it);
  }
  return absl::OkStatus();
}

// Versions and kinds of the layouts Save writes.
constexpr uint32_t kHnswFormat = 0x484e5731;    // "HNW1"
constexpr uint32_t kTieredFormat = 0x54524431;  // "TRD1"

absl::Status HnswIndex::Save(core::ByteWriter& out) const {
  out.Put<uint32_t>(kHnswFormat);
  try {
    graph_->Save(out);
  } catch (const std::system_error& e) {
    return FloatsNotRead(e,
                         "the codes' floats could not be read for a snapshot");
  }
  out.Put<uint64_t>(id_of_.size());
  out.PutBytes(id_of_.data(), id_of_.size() * sizeof(uint64_t));
  return absl::OkStatus();
}

absl::Status HnswIndex::Load(core::ByteReader& in) {
  if (!slot_of_.empty()) {
    return absl::FailedPreconditionError("HNSW index: Load into a used index");
  }
  uint32_t format = 0;
  if (!in.Get(&format) || format != kHnswFormat) {
    return absl::DataLossError("HNSW index snapshot: unknown format");
  }
  absl::StatusOr<std::unique_ptr<core::HnswGraph>> graph =
      core::HnswGraph::Load(dimension(), GraphOptions(options_), in);
  if (!graph.ok()) return graph.status();
  uint64_t slots = 0;
  if (!in.Get(&slots) || slots != (*graph)->slot_count()) {
    return absl::DataLossError("HNSW index snapshot: bad slot count");
  }
  try {
    std::vector<uint64_t> id_of(slots);
    in.GetBytes(id_of.data(), slots * sizeof(uint64_t));
    absl::flat_hash_map<uint64_t, uint32_t> slot_of;
    slot_of.reserve((*graph)->size());
    for (uint32_t slot = 0; slot < slots; ++slot) {
      if ((*graph)->contains(slot) &&
          !slot_of.emplace(id_of[slot], slot).second) {
        return absl::DataLossError(absl::StrCat("HNSW index snapshot: id ",
                                                id_of[slot], " held twice"));
      }
    }
    graph_ = *std::move(graph);
    id_of_ = std::move(id_of);
    slot_of_ = std::move(slot_of);
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("HNSW index: out of memory in Load");
  }
  return absl::OkStatus();
}

std::vector<Neighbor> HnswIndex::Scan(std::span<const float> query, float scale,
                                      const SearchParams& params) const {
  std::vector<Neighbor> all;
  all.reserve(slot_of_.size());
  graph_->ScanPrecise(
      query.data(), scale,
      [&](uint32_t slot) {
        return !params.accept || params.accept(id_of_[slot]);
      },
      [&](uint32_t slot, double squared) {
        all.push_back({id_of_[slot], static_cast<float>(std::sqrt(squared))});
      });
  return all;
}

bool HnswIndex::CopyCodes(std::span<const uint64_t> ids,
                          std::span<std::vector<float>* const> codes) const {
  std::vector<uint32_t> slots;
  std::vector<float*> out;
  bool all = true;
  for (size_t i = 0; i < ids.size(); ++i) {
    auto it = slot_of_.find(ids[i]);
    if (it == slot_of_.end()) {
      all = false;
      continue;
    }
    codes[i]->resize(dimension());
    slots.push_back(it->second);
    out.push_back(codes[i]->data());
  }
  try {
    graph_->CopyVectors(slots, out);
  } catch (const std::system_error& e) {
    // The floats' file could not be read: the caller says which codes are
    // missing (an INTERNAL status naming the trace), and the log says why.
    FLEETMEM_LOG(kError) << FloatsNotRead(
        e,
        absl::StrCat("the codes of ", slots.size(), " ids could not be read"));
    for (size_t i = 0; i < ids.size(); ++i) {
      if (slot_of_.contains(ids[i])) codes[i]->clear();
    }
    return false;
  }
  return all;
}

absl::StatusOr<std::vector<Neighbor>> HnswIndex::Search(
    std::span<const float> query, const SearchParams& params) const {
  if (absl::Status status = CheckQuery(dimension(), query); !status.ok()) {
    return status;
  }
  const size_t live = slot_of_.size();
  if (live == 0 || params.k == 0) return std::vector<Neighbor>();
  const float scale = params.unit_query ? core::UnitScale(query) : 1.0f;
  try {
    size_t asked =
        (params.accept ? params.k * options_.accept_oversample : params.k) *
        (options_.codes == HnswIndexOptions::Codes::kInt8
             ? std::max<size_t>(options_.rescore_oversample, 1)
             : 1);
    while (true) {
      // Asking for half the index or more: a scan costs as much as the graph
      // search and, unlike it, reaches every vector (a graph can leave a
      // node unreachable).
      if (asked >= live / 2) {
        std::vector<Neighbor> all = Scan(query, scale, params);
        KeepNearest(all, params.k);
        return all;
      }
      // The graph's distances walk it; the answers are scored precisely,
      // their rows read in one batch.
      const size_t wanted = std::min(asked, live);
      std::vector<uint32_t> slots;
      for (const auto& [approximate, slot] :
           linking_ ? graph_->SearchBesideLinks(query.data(), wanted, scale)
                    : graph_->Search(query.data(), wanted, scale)) {
        if (params.accept && !params.accept(id_of_[slot])) continue;
        slots.push_back(slot);
      }
      const std::vector<double> squared =
          graph_->PreciseSquaredDistances(query.data(), slots, scale);
      std::vector<Neighbor> neighbors;
      neighbors.reserve(slots.size());
      for (size_t i = 0; i < slots.size(); ++i) {
        neighbors.push_back(
            {id_of_[slots[i]], static_cast<float>(std::sqrt(squared[i]))});
      }
      if (neighbors.size() >= params.k || asked >= live || !params.accept) {
        KeepNearest(neighbors, params.k);
        return neighbors;
      }
      asked *= 4;
    }
  } catch (const std::bad_alloc&) {
    return absl::ResourceExhaustedError("HNSW index: out of memory in Search");
  } catch (const std::system_error& e) {
    return FloatsNotRead(e, "the codes to rescore could not be read");
  }
}

// Vectors copied out of one index for another, with their ids and scales.
struct IdVectors {
  std::vector<uint64_t> ids;
  std::vector<std::vector<float>> vectors;
  std::vector<float> scales;
  std::function<void(uint64_t, std::span<const float>, float)> Collector() {
    return [this](uint64_t id, std::span<const float> vector, float scale) {
      ids.push_back(id);
      vectors.emplace_back(vector.begin(), vector.end());
      scales.push_back(scale);
    };
  }
};

// Counts a caller as waiting for a lock from construction until Acquired()
// (or destruction).
class WaiterCount {
 public:
  explicit WaiterCount(std::atomic<int>& waiters) : waiters_(waiters) {
    waiters_.fetch_add(1, std::memory_order_acq_rel);
  }
  ~WaiterCount() { Acquired(); }
  void Acquired() const {
    if (!acquired_) {
      acquired_ = true;
      waiters_.fetch_sub(1, std::memory_order_acq_rel);
    }
  }

 private:
  std::atomic<int>& waiters_;
  mutable bool acquired_ = false;
};

// The exact index alone below options.hnsw_from vectors; from it on an HNSW
// graph plus an exact growing segment (tail_) that a background thread
// drains into the graph. One reader/writer lock guards both, so a Search
// sees every vector exactly once: in the tail or in the graph.
class TieredIndex final : public engine::PlaceIndex {
 public:
  TieredIndex(size_t dimension, TieredIndexOptions options)
      : dimension_(dimension),
        options_(options),
        tail_(NewExactIndex(dimension)) {
    if (options_.indexer_batch == 0) {
      options_.indexer_batch =
          options_.hnsw.codes == HnswIndexOptions::Codes::kInt8 ? 2 : 1;
    }
    options_.hnsw.insert_threads =
        std::max<size_t>(1, options_.hnsw.insert_threads);
  }
  ~TieredIndex() override {
    {
      std::unique_lock lock(mu_);
      stop_ = true;
    }
    changed_.notify_all();
    if (indexer_.joinable()) indexer_.join();
  }

  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override {
    return AddToTail(ids, [&] { return tail_->Add(ids, vectors); });
  }
  absl::Status AddNormalized(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) override {
    return AddToTail(ids, [&] { return tail_->AddNormalized(ids, codes); });
  }
  absl::Status AddNormalizedUnthrottled(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) override {
    return AddToTail(
        ids, [&] { return tail_->AddNormalized(ids, codes); },
        /*back_pressure=*/false);
  }
  absl::Status CatchUp(size_t added) override;
  absl::Status Remove(std::span<const uint64_t> ids) override;
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override;
  size_t size() const override {
    std::shared_lock lock(mu_);
    return SizeLocked();
  }
  size_t dimension() const override { return dimension_; }

  void set_ef_search(size_t ef) {
    std::unique_lock lock(mu_);
    options_.hnsw.ef_search = ef;
    if (graph_) graph_->set_ef_search(ef);
  }
  size_t WaitIdle() {
    std::unique_lock lock(mu_);
    changed_.wait(lock, [this] { return Idle(); });
    return graph_ ? tail_->size() : 0;
  }
  size_t unindexed() const override {
    std::shared_lock lock(mu_);
    return graph_ ? tail_->size() : 0;
  }
  void DeferIndexing(absl::Time until) override {
    {
      std::unique_lock lock(mu_);
      deferred_until_ = until;
    }
    changed_.notify_all();
  }
  absl::Status IndexWaiting() override;
  // Both tiers keep codes as given, and move them between each other so.
  bool HoldsCode(uint64_t id) const override {
    std::shared_lock lock(mu_);
    return HoldsCodeLocked(id);
  }
  // One turn of the lock for all: the engine asks for a million ids after
  // a load, while the background thread takes the lock between steps.
  std::vector<bool> HoldsCodes(std::span<const uint64_t> ids) const override {
    std::vector<bool> held(ids.size());
    std::shared_lock lock(mu_);
    for (size_t i = 0; i < ids.size(); ++i) held[i] = HoldsCodeLocked(ids[i]);
    return held;
  }
  bool CopyCode(uint64_t id, std::vector<float>* code) const override {
    std::shared_lock lock(mu_);
    return CopyCodeLocked(id, code);
  }
  bool CopyCodes(std::span<const uint64_t> ids,
                 std::span<std::vector<float>* const> codes) const override {
    std::shared_lock lock(mu_);
    return CopyCodesLocked(ids, codes);
  }
  // The tail and the graph as they are: a backlog is saved as a backlog.
  absl::Status Save(core::ByteWriter& out) const override;
  void SavedToFile() override {
    std::unique_lock lock(mu_);
    if (graph_) graph_->SavedToFile();
  }
  absl::Status Load(core::ByteReader& in) override;
  bool Damaged() const override {
    std::shared_lock lock(mu_);
    return graph_ != nullptr && graph_->Damaged();
  }

 private:
  // Add and AddNormalized: `add` stores the batch in the tail (it checks
  // the batch and the tail's ids; AddToTail the graph's); then the graph
  // starts, or, with `back_pressure`, the backlog is bounded.
  absl::Status AddToTail(std::span<const uint64_t> ids,
                         const std::function<absl::Status()>& add,
                         bool back_pressure = true);
  // The members below mu_ and the functions up to IndexerLoop need mu_
  // (shared for reading). std::shared_mutex and a condition variable rather
  // than absl::Mutex::Await: ThreadSanitizer sees these waits (`make
  // test-tsan`; Debian's absl is not instrumented).
  size_t SizeLocked() const {
    // A linking step's vectors are in both tiers.
    return tail_->size() + (graph_ ? graph_->size() : 0) - linking_count_;
  }
  bool CopyCodeLocked(uint64_t id, std::vector<float>* code) const {
    return tail_->CopyCode(id, code) || (graph_ && graph_->CopyCode(id, code));
  }
  // The tail's codes one by one, the graph's in one batch.
  bool CopyCodesLocked(std::span<const uint64_t> ids,
                       std::span<std::vector<float>* const> codes) const {
    std::vector<uint64_t> graph_ids;
    std::vector<std::vector<float>*> graph_codes;
    for (size_t i = 0; i < ids.size(); ++i) {
      if (tail_->CopyCode(ids[i], codes[i])) continue;
      graph_ids.push_back(ids[i]);
      graph_codes.push_back(codes[i]);
    }
    if (graph_ids.empty()) return true;
    return graph_ != nullptr && graph_->CopyCodes(graph_ids, graph_codes);
  }
  bool HoldsCodeLocked(uint64_t id) const {
    return tail_->HoldsCode(id) || (graph_ && graph_->contains(id));
  }
  // Nothing for the background thread to do (now: a deferral ends).
  bool Idle() const {
    return stop_ || !graph_ || tail_->size() == 0 || paused_ || Deferred();
  }
  bool Deferred() const { return absl::Now() < deferred_until_; }
  // Moves up to `count` vectors from the end of the tail into the graph,
  // under `lock` (of mu_), which it gives up while the new nodes are linked:
  // searches and readers go on under the shared lock meanwhile, and the
  // moved vectors stay in the tail until they are linked (Search keeps
  // each id once). Waits for another caller's move first.
  absl::Status MoveToGraph(size_t count,
                           std::unique_lock<std::shared_mutex>& lock);
  // Waits, under `lock` (of mu_, exclusive or shared), until no move is
  // linking: writers that change the graph or the tail's moved vectors.
  template <typename Lock>
  void AwaitLinked(Lock& lock) const {
    changed_.wait(lock, [this] { return !linking_; });
  }
  // Vectors moved into the graph per step under the lock.
  size_t StepSize() const {
    return options_.indexer_batch * options_.hnsw.insert_threads;
  }
  // Vectors IndexWaiting moves per step: large enough that linking them on
  // the insert threads keeps every thread busy, small enough that the
  // step's copy of its vectors stays small (50 MiB at 256-d).
  static constexpr size_t kBuildStep = 50'000;
  // Makes the graph once the tail holds hnsw_from vectors (and starts the
  // background thread). Under mu_, exclusive.
  void StartGraphIfDue();
  // CatchUp's work, under `lock` (of mu_).
  absl::Status CatchUpLocked(size_t count,
                             std::unique_lock<std::shared_mutex>& lock);
  // Unlocks, waits until no caller is waiting for mu_, and locks again.
  void YieldToWaiters(std::unique_lock<std::shared_mutex>& lock);
  // Moves every graph vector back into the tail and drops the graph.
  absl::Status DropGraph();
  void IndexerLoop();

  const size_t dimension_;
  mutable std::shared_mutex mu_;
  // Signalled when there is work for the background thread or it made
  // progress, stopped or paused.
  mutable std::condition_variable_any changed_;
  TieredIndexOptions options_;
  // Vectors not in the graph (all of them while there is no graph).
  std::unique_ptr<engine::PlaceIndex> tail_;
  std::unique_ptr<HnswIndex> graph_;
  // A MoveToGraph is linking its step beside readers (mu_ shared), of
  // linking_count_ vectors (in the tail and the graph meanwhile).
  bool linking_ = false;
  size_t linking_count_ = 0;
  // The background thread stopped on an error; the next Add resumes it.
  bool paused_ = false;
  // DeferIndexing's: no graph is built nor linked before this time, and
  // no back-pressure applies.
  absl::Time deferred_until_ = absl::InfinitePast();
  bool stop_ = false;
  // Callers of Search, Add and Remove waiting for mu_; the background
  // thread lets them all in before its next step.
  mutable std::atomic<int> waiters_{0};
  // Callers of Add and Remove waiting for mu_; new searches wait for them.
  std::atomic<int> writers_{0};
  std::thread indexer_;  // started with the first graph
};

absl::Status TieredIndex::AddToTail(std::span<const uint64_t> ids,
                                    const std::function<absl::Status()>& add,
                                    bool back_pressure) {
  const WaiterCount turn(waiters_);
  const WaiterCount writer(writers_);
  std::unique_lock lock(mu_);
  turn.Acquired();
  writer.Acquired();
  if (graph_) {
    for (uint64_t id : ids) {
      if (graph_->contains(id)) {
        return absl::InvalidArgumentError(
            absl::StrCat("id ", id, " is already in the index"));
      }
    }
  }
  const size_t waiting = graph_ ? tail_->size() : 0;
  absl::Status status = add();
  if (!status.ok()) return status;
  StartGraphIfDue();
  // Deferred: IndexWaiting builds the graph, or the background thread
  // once the deferral lapses.
  if (!graph_ || Deferred()) return absl::OkStatus();
  paused_ = false;
  if (!options_.background) return MoveToGraph(tail_->size(), lock);
  changed_.notify_all();
  if (!back_pressure || waiting <= options_.max_unindexed) {
    return absl::OkStatus();
  }
  return CatchUpLocked(ids.size(), lock);
}

void TieredIndex::StartGraphIfDue() {
  if (graph_ || tail_->size() < options_.hnsw_from) return;
  graph_ = std::make_unique<HnswIndex>(dimension_, options_.hnsw);
  if (options_.background && !indexer_.joinable()) {
    indexer_ = std::thread([this] { IndexerLoop(); });
  }
}

absl::Status TieredIndex::CatchUp(size_t added) {
  const WaiterCount turn(waiters_);
  const WaiterCount writer(writers_);
  std::unique_lock lock(mu_);
  turn.Acquired();
  writer.Acquired();
  if (!graph_ || tail_->size() <= options_.max_unindexed || Deferred()) {
    return absl::OkStatus();
  }
  return CatchUpLocked(added, lock);
}

absl::Status TieredIndex::IndexWaiting() {
  const WaiterCount turn(waiters_);
  const WaiterCount writer(writers_);
  std::unique_lock lock(mu_);
  turn.Acquired();
  writer.Acquired();
  deferred_until_ = absl::InfinitePast();
  StartGraphIfDue();
  paused_ = false;
  changed_.notify_all();
  // Large steps, each linked on every insert thread; searches (an exact
  // scan of what still waits beside the graph) go on between and beside
  // them. The background thread may take steps too: the same work.
  while (graph_ && tail_->size() > 0) {
    absl::Status status = MoveToGraph(kBuildStep, lock);
    if (!status.ok()) return status;
    YieldToWaiters(lock);
  }
  return absl::OkStatus();
}

absl::Status TieredIndex::CatchUpLocked(
    size_t count, std::unique_lock<std::shared_mutex>& lock) {
  // Back-pressure: up to `count` vectors move into the graph while more
  // than max_unindexed wait, a step at a time with every waiting caller let
  // in between steps, so that a Search waits for one step, not the batch.
  for (size_t left = count;
       left > 0 && graph_ && tail_->size() > options_.max_unindexed;) {
    const size_t step = std::min(left, StepSize());
    absl::Status status = MoveToGraph(step, lock);
    if (!status.ok()) return status;
    left -= step;
    if (left > 0) YieldToWaiters(lock);
  }
  return absl::OkStatus();
}

void TieredIndex::YieldToWaiters(std::unique_lock<std::shared_mutex>& lock) {
  // The lock is not fair: a thread that re-locks at once would starve them.
  // With nobody waiting the lock is taken again at once (a sleep there cost
  // a quarter of a two-node step's time with int8 codes).
  lock.unlock();
  while (waiters_.load(std::memory_order_acquire) > 0) {
    absl::SleepFor(absl::Microseconds(50));
  }
  lock.lock();
}

absl::Status TieredIndex::Save(core::ByteWriter& out) const {
  std::shared_lock lock(mu_);
  AwaitLinked(lock);  // a graph with every link written
  out.Put<uint32_t>(kTieredFormat);
  absl::Status status = tail_->Save(out);
  if (!status.ok()) return status;
  out.Put<uint8_t>(graph_ ? 1 : 0);
  return graph_ ? graph_->Save(out) : absl::OkStatus();
}

absl::Status TieredIndex::Load(core::ByteReader& in) {
  std::unique_lock lock(mu_);
  if (SizeLocked() != 0) {
    return absl::FailedPreconditionError(
        "tiered index: Load into a used index");
  }
  uint32_t format = 0;
  uint8_t has_graph = 0;
  if (!in.Get(&format) || format != kTieredFormat) {
    return absl::DataLossError("tiered index snapshot: unknown format");
  }
  absl::Status status = tail_->Load(in);
  if (status.ok() && !in.Get(&has_graph)) {
    status = absl::DataLossError("tiered index snapshot: truncated");
  }
  if (status.ok() && has_graph != 0) {
    graph_ = std::make_unique<HnswIndex>(dimension_, options_.hnsw);
    status = graph_->Load(in);
    ForEachExactVector(*tail_, [&](uint64_t id, std::span<const float>, float) {
      if (status.ok() && graph_->contains(id)) {
        status = absl::DataLossError(absl::StrCat(
            "tiered index snapshot: id ", id, " in the tail and the graph"));
      }
    });
  }
  if (!status.ok()) {
    tail_ = NewExactIndex(dimension_);
    graph_.reset();
    return status;
  }
  if (graph_ && options_.background && !indexer_.joinable()) {
    indexer_ = std::thread([this] { IndexerLoop(); });
  }
  changed_.notify_all();
  return absl::OkStatus();
}

absl::Status TieredIndex::Remove(std::span<const uint64_t> ids) {
  const WaiterCount turn(waiters_);
  const WaiterCount writer(writers_);
  std::unique_lock lock(mu_);
  turn.Acquired();
  writer.Acquired();
  AwaitLinked(lock);
  absl::Status status = tail_->Remove(ids);
  if (status.ok() && graph_) status = graph_->Remove(ids);
  if (status.ok() && graph_ && SizeLocked() < options_.hnsw_from / 2) {
    status = DropGraph();
  }
  changed_.notify_all();
  return status;
}

absl::StatusOr<std::vector<Neighbor>> TieredIndex::Search(
    std::span<const float> query, const SearchParams& params) const {
  // glibc's reader/writer lock prefers readers: a steady stream of
  // searches would starve the engine's Add and Remove, so searches let a
  // waiting writer in first.
  while (writers_.load(std::memory_order_acquire) > 0) {
    absl::SleepFor(absl::Microseconds(20));
  }
  const WaiterCount turn(waiters_);
  std::shared_lock lock(mu_);
  turn.Acquired();
  // The tiers leave params.codes alone; the codes are copied below.
  absl::StatusOr<std::vector<Neighbor>> found = tail_->Search(query, params);
  if (!found.ok()) return found;
  if (graph_) {
    absl::StatusOr<std::vector<Neighbor>> graphed =
        graph_->Search(query, params);
    if (!graphed.ok()) return graphed;
    found->insert(found->end(), graphed->begin(), graphed->end());
    KeepNearestOnce(*found, params.k);
  }
  if (params.codes != nullptr) {
    params.codes->assign(found->size(), {});
    std::vector<uint64_t> ids;
    std::vector<std::vector<float>*> codes;
    for (size_t i = 0; i < found->size(); ++i) {
      ids.push_back((*found)[i].id);
      codes.push_back(&(*params.codes)[i]);
    }
    // The caller's CopyCodes says which is missing.
    if (!CopyCodesLocked(ids, codes)) params.codes->clear();
  }
  return found;
}

absl::Status TieredIndex::MoveToGraph(
    size_t count, std::unique_lock<std::shared_mutex>& lock) {
  AwaitLinked(lock);
  const size_t size = tail_->size();
  count = std::min(count, size);
  if (count == 0 || !graph_) return absl::OkStatus();
  // Codes move as given, with their scales.
  IdVectors moved;
  ForEachExactVector(*tail_, moved.Collector(), size - count, size);
  absl::StatusOr<core::HnswGraph::Staged> staged =
      graph_->StageScaled<std::vector<float>>(
          moved.ids, moved.vectors,
          [&](size_t i, std::span<const float>) { return moved.scales[i]; });
  if (!staged.ok()) return staged.status();
  // Linking is most of a step's cost: readers go on beside it.
  linking_ = true;
  linking_count_ = staged->slots.size();
  graph_->set_linking(true);
  lock.unlock();
  absl::Status status;
  {
    std::shared_lock shared(mu_);
    status = graph_->LinkStaged(*staged, moved.ids.size());
  }
  lock.lock();
  graph_->set_linking(false);
  linking_ = false;
  linking_count_ = 0;
  changed_.notify_all();
  // The tail gives its storage back as it drains (the exact index shrinks);
  // vectors the graph could not take stay in it.
  moved.ids.resize(staged->slots.size());
  absl::Status removed = tail_->Remove(moved.ids);
  return status.ok() ? removed : status;
}

absl::Status TieredIndex::DropGraph() {
  // Codes go back as given: plain vectors (scale 1) through Add, scaled
  // ones through AddNormalized, which gives them the same scale again.
  IdVectors plain, scaled;
  try {
    graph_->ForEach(
        [&](uint64_t id, std::span<const float> vector, float scale) {
          (scale == 1.0f ? plain : scaled).Collector()(id, vector, scale);
        });
  } catch (const std::system_error& e) {
    return absl::InternalError(absl::StrCat(
        "tiered index: the graph's codes could not be read back (the graph "
        "is kept): ",
        e.what()));
  }
  std::vector<std::span<const float>> codes(scaled.vectors.begin(),
                                            scaled.vectors.end());
  absl::Status status = tail_->Add(plain.ids, plain.vectors);
  if (status.ok()) status = tail_->AddNormalized(scaled.ids, codes);
  if (!status.ok()) {
    (void)tail_->Remove(plain.ids);
    return status;
  }
  graph_.reset();
  return absl::OkStatus();
}

void TieredIndex::IndexerLoop() {
  if (absl::Status marked =
          common::MarkBackgroundThread("fleetmem-graph", options_.indexer_nice);
      !marked.ok()) {
    FLEETMEM_LOG(kWarning) << "tiered index: " << marked;
  }
  std::unique_lock lock(mu_);
  while (true) {
    if (Idle() && !stop_) {
      // A deferral ends by itself: wake then.
      if (Deferred() && deferred_until_ != absl::InfiniteFuture()) {
        changed_.wait_until(lock, absl::ToChronoTime(deferred_until_));
      } else {
        changed_.wait(lock);
      }
      continue;
    }
    if (stop_) break;
    absl::Status status = MoveToGraph(StepSize(), lock);
    if (!status.ok()) {
      FLEETMEM_LOG(kError) << "tiered index: " << tail_->size()
                           << " vectors stay in the exact segment: " << status;
      paused_ = true;
    }
    changed_.notify_all();  // progress or a pause, for WaitIdle
    YieldToWaiters(lock);   // searches and writers go first
  }
}

}  // namespace

std::unique_ptr<engine::PlaceIndex> NewHnswIndex(size_t dimension,
                                                 HnswIndexOptions options) {
  return std::make_unique<HnswIndex>(dimension, options);
}

std::optional<HnswIndexOptions::Codes> ParseHnswCodes(std::string_view word) {
  if (word == "float") return HnswIndexOptions::Codes::kFloat;
  if (word == "int8") return HnswIndexOptions::Codes::kInt8;
  return std::nullopt;
}

std::string_view HnswCodesName(HnswIndexOptions::Codes codes) {
  return codes == HnswIndexOptions::Codes::kInt8 ? "int8" : "float";
}

size_t HnswMemoryBytes(const engine::PlaceIndex& index) {
  const auto* hnsw = dynamic_cast<const HnswIndex*>(&index);
  return hnsw == nullptr ? 0 : hnsw->graph_bytes();
}

bool SetHnswEfSearch(engine::PlaceIndex& index, size_t ef_search) {
  if (auto* tiered = dynamic_cast<TieredIndex*>(&index)) {
    tiered->set_ef_search(ef_search);
    return true;
  }
  auto* hnsw = dynamic_cast<HnswIndex*>(&index);
  if (hnsw == nullptr) return false;
  hnsw->set_ef_search(ef_search);
  return true;
}

size_t WaitForIndexing(engine::PlaceIndex& index) {
  auto* tiered = dynamic_cast<TieredIndex*>(&index);
  return tiered == nullptr ? 0 : tiered->WaitIdle();
}

std::unique_ptr<engine::PlaceIndex> NewTieredIndex(size_t dimension,
                                                   TieredIndexOptions options) {
  return std::make_unique<TieredIndex>(dimension, options);
}

}  // namespace fleetmem::index
