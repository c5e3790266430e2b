// Test helpers of the engine's tests (memory_engine*_test.cc, and the
// cluster's and metrics' tests that run an engine): options small enough
// that a few uploads exercise every path, traces, index and store doubles,
// and the MemoryEngineTest fixture. Here, above the engine, the storage
// and the index that it assembles (services/testing: fixtures of several
// modules; no production code includes them).
#ifndef FLEETMEM_SERVICES_TESTING_MEMORY_ENGINE_TEST_UTIL_H_
#define FLEETMEM_SERVICES_TESTING_MEMORY_ENGINE_TEST_UTIL_H_

#include <atomic>
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <cstdint>
#include <cstring>
#include <functional>
#include <future>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/engine/memory_engine.h"
#include "services/engine/testing/forwarding_store.h"
#include "services/index/exact_index.h"
#include "services/index/hnsw_index.h"
#include "services/storage/in_memory_store.h"

namespace fleetmem::engine {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::SizeIs;

constexpr size_t kDimension = 8;

// Options small enough that a few uploads exercise every path.
inline EngineOptions SmallOptions() {
  EngineOptions options;
  options.memory.clusters_per_batch = 4;
  options.memory.max_traces_per_cluster = 3;
  options.memory.max_clusters = 5;
  options.segment_size = 20;
  options.max_traces_per_upload = 50;
  options.max_sample_count = 100;
  options.max_query_k = 200;
  options.max_events_per_read = 1000;
  return options;
}

inline PlaceIndexFactory ExactFactory() {
  return [](size_t dimension) { return index::NewExactIndex(dimension); };
}

// The fleet's events are exactly those with ids 1..last, in order.
inline void ExpectEventIds1To(const MemoryEngine& engine,
                              std::string_view fleet_id, uint64_t last) {
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine.ReadEvents(fleet_id, 0);
  ASSERT_TRUE(events.ok()) << events.status();
  ASSERT_EQ(events->size(), last);
  for (size_t i = 0; i < events->size(); ++i) {
    EXPECT_EQ((*events)[i].id, i + 1);
  }
}

// An engine with exact indexes on `store`; null (and a test failure) if it
// does not open.
inline std::unique_ptr<MemoryEngine> OpenOn(const EngineOptions& options,
                                            MemoryStore* store) {
  absl::StatusOr<std::unique_ptr<MemoryEngine>> engine =
      MemoryEngine::Open(options, store, ExactFactory());
  EXPECT_TRUE(engine.ok()) << engine.status();
  return engine.ok() ? *std::move(engine) : nullptr;
}

// A trace with a random code whose place lies on the x axis at 5 m * seq.
inline core::MemoryTrace MakeTrace(std::string robot_id, uint64_t seq,
                                   std::mt19937_64& rng, float reward = 1.0f,
                                   size_t dimension = kDimension) {
  std::normal_distribution<float> normal;
  core::MemoryTrace trace;
  trace.robot_id = std::move(robot_id);
  trace.seq = seq;
  trace.domain = seq % 2 == 0 ? "summer" : "winter";
  trace.code.resize(dimension);
  for (float& value : trace.code) value = normal(rng);
  trace.place = core::Place{5.0 * static_cast<double>(seq), 0.0, 0.0, 0.0};
  trace.reward = reward;
  trace.timestamp_ns = static_cast<int64_t>(seq) * 1000;
  trace.encoder_version = "v1";
  return trace;
}

inline std::vector<core::MemoryTrace> MakeTraces(const std::string& robot_id,
                                                 uint64_t first_seq,
                                                 size_t count,
                                                 std::mt19937_64& rng) {
  std::vector<core::MemoryTrace> traces;
  for (size_t i = 0; i < count; ++i) {
    traces.push_back(MakeTrace(robot_id, first_seq + i, rng));
  }
  return traces;
}

// Forwards every call to an inner index.
class ForwardingIndex : public PlaceIndex {
 public:
  explicit ForwardingIndex(std::unique_ptr<PlaceIndex> inner)
      : inner_(std::move(inner)) {}
  absl::Status Add(std::span<const uint64_t> ids,
                   std::span<const std::vector<float>> vectors) override {
    return inner_->Add(ids, vectors);
  }
  absl::Status AddNormalized(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) override {
    return inner_->AddNormalized(ids, codes);
  }
  absl::Status AddNormalizedUnthrottled(
      std::span<const uint64_t> ids,
      std::span<const std::span<const float>> codes) override {
    return inner_->AddNormalizedUnthrottled(ids, codes);
  }
  absl::Status CatchUp(size_t added) override { return inner_->CatchUp(added); }
  absl::Status Remove(std::span<const uint64_t> ids) override {
    return inner_->Remove(ids);
  }
  absl::StatusOr<std::vector<Neighbor>> Search(
      std::span<const float> query, const SearchParams& params) const override {
    return inner_->Search(query, params);
  }
  size_t size() const override { return inner_->size(); }
  size_t dimension() const override { return inner_->dimension(); }
  bool HoldsCode(uint64_t id) const override { return inner_->HoldsCode(id); }
  bool CopyCode(uint64_t id, std::vector<float>* code) const override {
    return inner_->CopyCode(id, code);
  }
  absl::Status Save(core::ByteWriter& out) const override {
    return inner_->Save(out);
  }
  absl::Status Load(core::ByteReader& in) override { return inner_->Load(in); }
  bool Damaged() const override { return inner_->Damaged(); }

 protected:
  std::unique_ptr<PlaceIndex> inner_;
};

// An HNSW index (which keeps every code it is given) whose HoldsCode the
// test switches on, counting the codes the engine reads back.
class SwitchedCodeIndex final : public ForwardingIndex {
 public:
  struct Switch {
    std::atomic<bool> holds{false};
    std::atomic<int> copies{0};
  };
  SwitchedCodeIndex(size_t dimension, std::shared_ptr<Switch> control)
      : ForwardingIndex(index::NewHnswIndex(dimension)),
        control_(std::move(control)) {}
  bool HoldsCode(uint64_t id) const override {
    return control_->holds && inner_->HoldsCode(id);
  }
  bool CopyCode(uint64_t id, std::vector<float>* code) const override {
    if (!control_->holds) return false;
    ++control_->copies;
    return inner_->CopyCode(id, code);
  }

 private:
  std::shared_ptr<Switch> control_;
};

// Every trace of the static memory (QueryPlace with the largest k).
inline std::vector<core::MemoryTrace> AllTraces(const MemoryEngine& engine,
                                                std::string_view fleet_id,
                                                size_t max_k) {
  PlaceQuery query;
  query.code.assign(kDimension, 1.0f);
  query.k = max_k;
  absl::StatusOr<std::vector<PlaceMatch>> matches =
      engine.QueryPlace(fleet_id, query);
  EXPECT_TRUE(matches.ok()) << matches.status();
  std::vector<core::MemoryTrace> traces;
  if (!matches.ok()) return traces;
  for (PlaceMatch& match : *matches) traces.push_back(std::move(match.trace));
  return traces;
}

// Forwards every call to another store; the stores below override Apply.
// Each of `traces` is its own nearest match in fleet "f1", at distance 0.
inline void ExpectEachTraceFindsItself(
    const MemoryEngine& engine, const std::vector<core::MemoryTrace>& traces) {
  for (const core::MemoryTrace& trace : traces) {
    PlaceQuery query;
    query.code = trace.code;
    absl::StatusOr<std::vector<PlaceMatch>> matches =
        engine.QueryPlace("f1", query);
    ASSERT_TRUE(matches.ok()) << matches.status();
    ASSERT_EQ(matches->size(), 1u);
    EXPECT_EQ(matches->front().trace.key(), trace.key());
    EXPECT_EQ(matches->front().distance, 0.0f);
  }
}

// A store whose index snapshots, once written and before their (simulated)
// sync, run `during_sync` on another thread and wait for it: the engine
// must let the fleet change by then.
class SlowSyncStore : public ForwardingStore {
 public:
  SlowSyncStore(MemoryStore* inner, std::function<void()> during_sync)
      : ForwardingStore(inner),
        inner_(inner),
        during_sync_(std::move(during_sync)) {}
  absl::Status SaveIndexSnapshot(
      std::string_view fleet_id,
      const std::function<absl::Status(core::ByteWriter&)>& write,
      const std::function<void()>& written) override {
    return inner_->SaveIndexSnapshot(fleet_id, write, [&] {
      if (written) written();
      std::packaged_task<void()> task(during_sync_);
      std::future<void> done = task.get_future();
      std::thread thread(std::move(task));
      if (done.wait_for(std::chrono::seconds(20)) !=
          std::future_status::ready) {
        ADD_FAILURE() << "the fleet stayed locked while its snapshot synced";
        std::abort();  // the thread cannot be joined: fail loudly
      }
      thread.join();
    });
  }
  absl::Status ReadIndexSnapshot(
      std::string_view fleet_id,
      const engine::IndexSnapshotRead& read) override {
    return inner_->ReadIndexSnapshot(fleet_id, read);
  }

 private:
  MemoryStore* inner_;
  std::function<void()> during_sync_;
};

// A store that fails Apply after `fail_after` successful calls.
class FlakyStore : public ForwardingStore {
 public:
  using ForwardingStore::ForwardingStore;
  absl::Status Apply(std::string_view fleet_id,
                     const FleetMutation& mutation) override {
    ++applies;
    if (fail_after >= 0 && applies > fail_after) return failure;
    return ForwardingStore::Apply(fleet_id, mutation);
  }

  int applies = 0;
  int fail_after = -1;  // Apply calls that succeed before failures; -1: never
  absl::Status failure = absl::InternalError("disk on fire");
};

// A store whose Apply, while held, waits until Release(): a slow fsync that
// a test controls.
class GatedStore : public ForwardingStore {
 public:
  using ForwardingStore::ForwardingStore;
  absl::Status Apply(std::string_view fleet_id,
                     const FleetMutation& mutation) override {
    if (!hold_after_write_) Wait();
    absl::Status status = ForwardingStore::Apply(fleet_id, mutation);
    if (hold_after_write_) Wait();
    return status;
  }
  // Apply calls wait from now until Release; with `after_write`, once the
  // write is made (the store holds it, its caller has not heard yet).
  void Hold(bool after_write = false) {
    std::unique_lock lock(mu_);
    hold_ = true;
    hold_after_write_ = after_write;
  }
  // Blocks until `count` Apply calls are waiting.
  void AwaitWaiting(int count) {
    std::unique_lock lock(mu_);
    changed_.wait(lock, [this, count] { return waiting_ >= count; });
  }
  void Release() {
    {
      std::unique_lock lock(mu_);
      hold_ = false;
    }
    changed_.notify_all();
  }

 private:
  // std::mutex rather than absl::Mutex::Await, which ThreadSanitizer does
  // not see (Debian's absl is not instrumented).
  void Wait() {
    std::unique_lock lock(mu_);
    if (!hold_) return;
    ++waiting_;
    changed_.notify_all();
    changed_.wait(lock, [this] { return !hold_; });
    --waiting_;
  }

  std::mutex mu_;
  std::condition_variable changed_;
  bool hold_ = false;
  std::atomic<bool> hold_after_write_ = false;
  int waiting_ = 0;
};

class MemoryEngineTest : public ::testing::Test {
 protected:
  void SetUp() override {
    store_ = storage::NewInMemoryStore();
    options_ = SmallOptions();
    options_.now_ns = [this] { return ++clock_ns_; };
    engine_ = OpenEngine();
  }

  std::unique_ptr<MemoryEngine> OpenEngine(EngineHooks hooks = {}) {
    absl::StatusOr<std::unique_ptr<MemoryEngine>> engine =
        MemoryEngine::Open(options_, store_.get(), ExactFactory(), hooks);
    EXPECT_TRUE(engine.ok()) << engine.status();
    return engine.ok() ? *std::move(engine) : nullptr;
  }

  FleetStats Stats(std::string_view fleet_id = "f1") {
    absl::StatusOr<FleetStats> stats = engine_->GetStats(fleet_id);
    EXPECT_TRUE(stats.ok()) << stats.status();
    return stats.ok() ? *stats : FleetStats{};
  }

  UploadResult MustUpload(std::span<const core::MemoryTrace> traces,
                          std::string_view fleet_id = "f1") {
    absl::StatusOr<UploadResult> result = engine_->Upload(fleet_id, traces);
    EXPECT_TRUE(result.ok()) << result.status();
    return result.ok() ? *result : UploadResult{};
  }

  std::mt19937_64 rng_{7};
  std::atomic<int64_t> clock_ns_{1000};  // read by concurrent fleets
  EngineOptions options_;
  std::unique_ptr<MemoryStore> store_;
  std::unique_ptr<MemoryEngine> engine_;
};

inline const RobotStats* FindRobot(const FleetStats& stats,
                                   std::string_view robot) {
  for (const RobotStats& entry : stats.robots) {
    if (entry.robot_id == robot) return &entry;
  }
  return nullptr;
}

// Compares every field of two stats.
inline void ExpectSameStats(const FleetStats& a, const FleetStats& b) {
  EXPECT_EQ(a.traces, b.traces);
  EXPECT_EQ(a.pending_traces, b.pending_traces);
  EXPECT_EQ(a.clusters, b.clusters);
  EXPECT_EQ(a.code_dimension, b.code_dimension);
  EXPECT_EQ(a.encoder_version, b.encoder_version);
  EXPECT_EQ(a.last_event_id, b.last_event_id);
  EXPECT_EQ(a.consolidations, b.consolidations);
  EXPECT_EQ(a.clusters_forgotten, b.clusters_forgotten);
  EXPECT_EQ(a.max_clusters, b.max_clusters);
  EXPECT_EQ(a.max_traces_per_cluster, b.max_traces_per_cluster);
  ASSERT_EQ(a.robots.size(), b.robots.size());
  for (size_t i = 0; i < a.robots.size(); ++i) {
    EXPECT_EQ(a.robots[i].robot_id, b.robots[i].robot_id);
    EXPECT_EQ(a.robots[i].traces, b.robots[i].traces);
    EXPECT_EQ(a.robots[i].pending_traces, b.robots[i].pending_traces);
    EXPECT_EQ(a.robots[i].max_seq, b.robots[i].max_seq);
    EXPECT_EQ(a.robots[i].received, b.robots[i].received);
    EXPECT_EQ(a.robots[i].replayed, b.robots[i].replayed);
  }
  ASSERT_EQ(a.domains.size(), b.domains.size());
  for (size_t i = 0; i < a.domains.size(); ++i) {
    EXPECT_EQ(a.domains[i].domain, b.domains[i].domain);
    EXPECT_EQ(a.domains[i].traces, b.domains[i].traces);
    EXPECT_EQ(a.domains[i].pending_traces, b.domains[i].pending_traces);
  }
}

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_TESTING_MEMORY_ENGINE_TEST_UTIL_H_
