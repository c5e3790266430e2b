#include "services/engine/memory_engine.h"

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
#include "services/engine/forwarding_store.h"
#include "services/index/exact_index.h"
#include "services/index/hnsw_index.h"
#include "services/storage/in_memory_store.h"

namespace fleetmem::engine {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::SizeIs;

constexpr size_t kDimension = 8;

// Options small enough that a few uploads exercise every path.
EngineOptions SmallOptions() {
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

PlaceIndexFactory ExactFactory() {
  return [](size_t dimension) { return index::NewExactIndex(dimension); };
}

// The fleet's events are exactly those with ids 1..last, in order.
void ExpectEventIds1To(const MemoryEngine& engine, std::string_view fleet_id,
                       uint64_t last) {
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
std::unique_ptr<MemoryEngine> OpenOn(const EngineOptions& options,
                                     MemoryStore* store) {
  absl::StatusOr<std::unique_ptr<MemoryEngine>> engine =
      MemoryEngine::Open(options, store, ExactFactory());
  EXPECT_TRUE(engine.ok()) << engine.status();
  return engine.ok() ? *std::move(engine) : nullptr;
}

// A trace with a random code whose place lies on the x axis at 5 m * seq.
core::MemoryTrace MakeTrace(std::string robot_id, uint64_t seq,
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

std::vector<core::MemoryTrace> MakeTraces(const std::string& robot_id,
                                          uint64_t first_seq, size_t count,
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
std::vector<core::MemoryTrace> AllTraces(const MemoryEngine& engine,
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
void ExpectEachTraceFindsItself(const MemoryEngine& engine,
                                const std::vector<core::MemoryTrace>& traces) {
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
      const std::function<absl::Status(std::span<const char>)>& read) override {
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
    if (fail_after >= 0 && applies > fail_after) {
      return absl::InternalError("disk on fire");
    }
    return ForwardingStore::Apply(fleet_id, mutation);
  }

  int applies = 0;
  int fail_after = -1;  // Apply calls that succeed before failures; -1: never
};

// A store whose Apply, while held, waits until Release(): a slow fsync that
// a test controls.
class GatedStore : public ForwardingStore {
 public:
  using ForwardingStore::ForwardingStore;
  absl::Status Apply(std::string_view fleet_id,
                     const FleetMutation& mutation) override {
    {
      std::unique_lock lock(mu_);
      if (hold_) {
        ++waiting_;
        changed_.notify_all();
        changed_.wait(lock, [this] { return !hold_; });
        --waiting_;
      }
    }
    return ForwardingStore::Apply(fleet_id, mutation);
  }
  void Hold() {
    std::unique_lock lock(mu_);
    hold_ = true;
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
  std::mutex mu_;
  std::condition_variable changed_;
  bool hold_ = false;
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

const RobotStats* FindRobot(const FleetStats& stats, std::string_view robot) {
  for (const RobotStats& entry : stats.robots) {
    if (entry.robot_id == robot) return &entry;
  }
  return nullptr;
}

// Compares every field of two stats.
void ExpectSameStats(const FleetStats& a, const FleetStats& b) {
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

TEST(ValidateEngineOptionsTest, RejectsZeroLimitsAndBadMemoryOptions) {
  EXPECT_TRUE(ValidateEngineOptions(EngineOptions{}).ok());
  EngineOptions options;
  options.segment_size = 0;
  EXPECT_EQ(ValidateEngineOptions(options).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(ValidateEngineOptions(options).message(),
              HasSubstr("segment_size"));
  options = EngineOptions{};
  options.max_query_k = 0;
  EXPECT_EQ(ValidateEngineOptions(options).code(),
            absl::StatusCode::kInvalidArgument);
  options = EngineOptions{};
  options.memory.max_clusters = 0;
  EXPECT_EQ(ValidateEngineOptions(options).code(),
            absl::StatusCode::kInvalidArgument);

  std::unique_ptr<MemoryStore> store = storage::NewInMemoryStore();
  options = EngineOptions{};
  options.max_events_per_read = 0;
  EXPECT_EQ(
      MemoryEngine::Open(options, store.get(), ExactFactory()).status().code(),
      absl::StatusCode::kInvalidArgument);
}

TEST(FleetMutationTest, EmptyOnlyWithoutChanges) {
  FleetMutation mutation;
  EXPECT_TRUE(mutation.empty());
  mutation.put_meta = true;
  EXPECT_FALSE(mutation.empty());
  mutation = FleetMutation{};
  mutation.erase_clusters.push_back(3);
  EXPECT_FALSE(mutation.empty());
  mutation = FleetMutation{};
  mutation.append_events.emplace_back();
  EXPECT_FALSE(mutation.empty());
}

TEST_F(MemoryEngineTest, UploadKeepsTracesPendingUntilSegmentIsFull) {
  std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 10, rng_);
  UploadResult result = MustUpload(traces);
  EXPECT_EQ(result.accepted, 10u);
  EXPECT_EQ(result.duplicates, 0u);
  EXPECT_EQ(result.consolidations, 0u);

  FleetStats stats = Stats();
  EXPECT_EQ(stats.pending_traces, 10u);
  EXPECT_EQ(stats.traces, 0u);
  EXPECT_EQ(stats.clusters, 0u);
  EXPECT_EQ(stats.code_dimension, kDimension);
  EXPECT_EQ(stats.encoder_version, "v1");
  EXPECT_EQ(stats.last_event_id, 0u);
  EXPECT_EQ(stats.max_clusters, 5u);
  EXPECT_EQ(stats.max_traces_per_cluster, 3u);
  ASSERT_THAT(stats.robots, SizeIs(1));
  EXPECT_EQ(stats.robots[0].robot_id, "r1");
  EXPECT_EQ(stats.robots[0].pending_traces, 10u);
  EXPECT_EQ(stats.robots[0].received, 10u);
  EXPECT_EQ(stats.robots[0].max_seq, 10u);
  ASSERT_THAT(stats.domains, SizeIs(2));
  EXPECT_EQ(stats.domains[0].domain, "summer");
  EXPECT_EQ(stats.domains[0].pending_traces, 5u);
  EXPECT_EQ(stats.domains[1].domain, "winter");
  EXPECT_EQ(stats.domains[1].pending_traces, 5u);
  EXPECT_THAT(engine_->ListFleets(), ElementsAre("f1"));
}

TEST_F(MemoryEngineTest, ConsolidatesAutomaticallyAtSegmentSize) {
  MustUpload(MakeTraces("r1", 1, 15, rng_));
  MustUpload(MakeTraces("r2", 1, 5, rng_));
  UploadResult result = MustUpload(MakeTraces("r1", 16, 5, rng_));
  EXPECT_EQ(result.accepted, 5u);
  EXPECT_EQ(result.consolidations, 1u);

  FleetStats stats = Stats();
  EXPECT_EQ(stats.consolidations, 1u);
  EXPECT_EQ(stats.pending_traces, 5u);  // r2 is below the segment size
  EXPECT_EQ(stats.clusters, 4u);        // K = 4
  EXPECT_GT(stats.traces, 0u);
  EXPECT_LE(stats.traces, 4u * 3u);  // N_max = 3
  EXPECT_EQ(stats.last_event_id, 4u);
  const RobotStats* r1 = FindRobot(stats, "r1");
  ASSERT_NE(r1, nullptr);
  EXPECT_EQ(r1->pending_traces, 0u);
  EXPECT_EQ(r1->traces, stats.traces);
  EXPECT_EQ(r1->received, 20u);
  const RobotStats* r2 = FindRobot(stats, "r2");
  ASSERT_NE(r2, nullptr);
  EXPECT_EQ(r2->pending_traces, 5u);

  // Queries see the static memory (r1, in clusters) and the pending traces
  // (r2, cluster 0); downsampled traces of r1 are gone from the index.
  size_t pending_matches = 0;
  std::vector<core::MemoryTrace> found = AllTraces(*engine_, "f1", 200);
  EXPECT_EQ(found.size(), stats.traces + stats.pending_traces);
  for (const core::MemoryTrace& trace : found) {
    if (trace.robot_id == "r1") {
      EXPECT_NE(trace.cluster_id, 0u);
    } else {
      EXPECT_EQ(trace.robot_id, "r2");
      EXPECT_EQ(trace.cluster_id, 0u);
      ++pending_matches;
    }
  }
  EXPECT_EQ(pending_matches, 5u);
}

// Distributed mode: an upload's log position is stored in the same write as
// the traces it adds, also when it fills a segment; one that adds nothing,
// or an older position, leaves it; a reopened engine reads it back.
TEST_F(MemoryEngineTest, LogPositionIsStoredWithTheTracesItAdds) {
  EXPECT_EQ(*engine_->LogPosition("f1"), 0u);  // no fleet yet
  const std::vector<core::MemoryTrace> first = MakeTraces("r1", 1, 10, rng_);
  ASSERT_TRUE(engine_->Upload("f1", first, 5).ok());
  EXPECT_EQ(*engine_->LogPosition("f1"), 5u);
  ASSERT_TRUE(engine_->Upload("f1", first, 9).ok());  // duplicates only
  EXPECT_EQ(*engine_->LogPosition("f1"), 5u);
  ASSERT_TRUE(engine_->Upload("f1", MakeTraces("r2", 1, 5, rng_), 3).ok());
  EXPECT_EQ(*engine_->LogPosition("f1"), 5u);  // older: kept
  ASSERT_TRUE(engine_->Upload("f1", MakeTraces("r2", 6, 5, rng_)).ok());
  EXPECT_EQ(*engine_->LogPosition("f1"), 5u);  // none given
  // Fills r1's segment: stored with its consolidation.
  absl::StatusOr<UploadResult> filled =
      engine_->Upload("f1", MakeTraces("r1", 11, 10, rng_), 12);
  ASSERT_TRUE(filled.ok()) << filled.status();
  EXPECT_EQ(filled->consolidations, 1u);
  EXPECT_EQ(*engine_->LogPosition("f1"), 12u);
  engine_.reset();
  engine_ = OpenEngine();
  EXPECT_EQ(*engine_->LogPosition("f1"), 12u);
  EXPECT_EQ(Stats().consolidations, 1u);
}

// Distributed mode's snapshots: a fleet exported from one engine and
// restored into another, over an older state of the same fleet there, is
// the same fleet: traces, clusters, counts, robots, events and position.
TEST_F(MemoryEngineTest, AnExportedFleetRestoresExactlyOverAnOlderState) {
  std::vector<std::vector<core::MemoryTrace>> uploads;
  for (uint64_t first = 1; first <= 80; first += 10) {
    uploads.push_back(MakeTraces("r1", first, 10, rng_));
    uploads.push_back(MakeTraces("r2", first, 10, rng_));
  }
  std::unique_ptr<MemoryStore> other_store = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> other = OpenOn(options_, other_store.get());
  ASSERT_NE(other, nullptr);
  for (size_t i = 0; i < uploads.size(); ++i) {
    ASSERT_TRUE(engine_->Upload("f1", uploads[i], i + 1).ok());
    // The other engine stopped a third of the way (its own position).
    if (i < uploads.size() / 3) {
      ASSERT_TRUE(other->Upload("f1", uploads[i], i + 1).ok());
    }
  }
  ASSERT_TRUE(engine_->SampleReplay("f1", "r1", 7, "req-1", 40).ok());
  ASSERT_GT(Stats().clusters_forgotten, 0u);

  absl::StatusOr<FleetImage> image = engine_->ExportFleet("f1", 42);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->record.meta.log_position, 42u);
  EXPECT_EQ(*engine_->LogPosition("f1"), 42u);  // recorded by the export
  ASSERT_TRUE(other->RestoreFleet("f1", *image).ok());

  const FleetStats want = Stats();
  absl::StatusOr<FleetStats> got = other->GetStats("f1");
  ASSERT_TRUE(got.ok()) << got.status();
  EXPECT_EQ(got->traces, want.traces);
  EXPECT_EQ(got->pending_traces, want.pending_traces);
  EXPECT_EQ(got->clusters, want.clusters);
  EXPECT_EQ(got->consolidations, want.consolidations);
  EXPECT_EQ(got->clusters_forgotten, want.clusters_forgotten);
  EXPECT_EQ(got->last_event_id, want.last_event_id);
  EXPECT_EQ(*other->LogPosition("f1"), 42u);
  absl::StatusOr<TracePage> a = engine_->ListTraces("f1", std::nullopt, 1000);
  absl::StatusOr<TracePage> b = other->ListTraces("f1", std::nullopt, 1000);
  ASSERT_TRUE(a.ok() && b.ok());
  ASSERT_EQ(a->traces.size(), b->traces.size());
  for (size_t i = 0; i < a->traces.size(); ++i) {
    EXPECT_EQ(a->traces[i].key(), b->traces[i].key());
    EXPECT_EQ(a->traces[i].cluster_id, b->traces[i].cluster_id);
    EXPECT_EQ(a->traces[i].replay_count, b->traces[i].replay_count);
    EXPECT_EQ(a->traces[i].code, b->traces[i].code);
  }
  ExpectEventIds1To(*other, "f1", want.last_event_id);
  // The retried sample is recognised on the restored fleet.
  absl::StatusOr<std::vector<core::MemoryTrace>> again =
      other->SampleReplay("f1", "r1", 7, "req-1", 43);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(other->GetStats("f1")->robots.front().replayed,
            Stats().robots.front().replayed);
  // And it survives a restart of its engine: the store holds it.
  other.reset();
  other = OpenOn(options_, other_store.get());
  ASSERT_NE(other, nullptr);
  EXPECT_EQ(other->GetStats("f1")->traces, want.traces);

  // Another fleet's image, or one without an upload, changes nothing.
  EXPECT_TRUE(absl::IsInvalidArgument(other->RestoreFleet("f2", *image)));
  FleetImage empty;
  empty.record.fleet_id = "f1";
  EXPECT_TRUE(absl::IsInvalidArgument(other->RestoreFleet("f1", empty)));
  EXPECT_EQ(other->GetStats("f1")->traces, want.traces);
  EXPECT_TRUE(absl::IsNotFound(engine_->ExportFleet("f9").status()));
}

// Every consolidated cluster reaches the store with its centroid (memory
// holds each centroid once, in forgetting's tracker, and hands it over).
TEST_F(MemoryEngineTest, StoredClustersCarryTheirCentroids) {
  MustUpload(MakeTraces("r1", 1, 20, rng_));
  absl::StatusOr<FleetRecord> record = store_->LoadFleet("f1");
  ASSERT_TRUE(record.ok()) << record.status();
  ASSERT_EQ(record->clusters.size(), 4u);
  for (const core::Cluster& cluster : record->clusters) {
    // A code's dimensions plus the place's three.
    EXPECT_EQ(cluster.centroid.size(),
              record->clusters.front().traces.front().code.size() + 3)
        << cluster.id;
  }
}

TEST_F(MemoryEngineTest, ConsolidateTakesEveryRobotsPendingTraces) {
  MustUpload(MakeTraces("r1", 1, 6, rng_));
  MustUpload(MakeTraces("r2", 1, 2, rng_));
  absl::StatusOr<ConsolidateResult> result = engine_->Consolidate("f1");
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->consolidated_traces, 8u);
  EXPECT_EQ(result->clusters_added, 4u + 2u);  // min(K, batch) per robot
  EXPECT_EQ(result->clusters_forgotten, 1u);   // 6 > K_max = 5
  EXPECT_EQ(result->clusters, 5u);
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok());
  // Forgetting merged the closest pair (the default): the survivor holds
  // both clusters' traces, at most N_max = 3, and the memory every trace
  // the merge did not drop.
  uint64_t dropped_traces = 0, merges = 0;
  for (const core::MemoryEvent& event : *events) {
    EXPECT_NE(event.type, core::EventType::kClusterForgotten);
    if (event.type == core::EventType::kClusterMerged) {
      ++merges;
      dropped_traces += event.traces_dropped;
      EXPECT_NE(event.merged_into, 0u);
      EXPECT_NE(event.merged_into, event.cluster_id);
    }
  }
  EXPECT_EQ(merges, 1u);
  EXPECT_EQ(result->traces, 8u - dropped_traces);
  EXPECT_EQ(result->downsampled_traces, dropped_traces);

  FleetStats stats = Stats();
  EXPECT_EQ(stats.pending_traces, 0u);
  EXPECT_EQ(stats.consolidations, 2u);  // one batch per robot
  EXPECT_EQ(stats.clusters, result->clusters);
  EXPECT_EQ(stats.traces, result->traces);
  EXPECT_EQ(stats.clusters_forgotten, 1u);
  EXPECT_EQ(stats.last_event_id, 6u + 1u);

  // Nothing pending: a second call changes nothing.
  absl::StatusOr<ConsolidateResult> again = engine_->Consolidate("f1");
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->consolidated_traces, 0u);
  EXPECT_EQ(again->clusters, 5u);
  EXPECT_EQ(Stats().consolidations, 2u);
}

TEST_F(MemoryEngineTest, UnknownFleetIsNotFound) {
  const std::string expected =
      "fleet \"nope\" does not exist (it is created by its first upload)";
  EXPECT_EQ(engine_->Consolidate("nope").status(),
            absl::NotFoundError(expected));
  EXPECT_EQ(engine_->GetStats("nope").status(), absl::NotFoundError(expected));
  EXPECT_EQ(engine_->SampleReplay("nope", "r1", 1).status(),
            absl::NotFoundError(expected));
  PlaceQuery query;
  query.code.assign(kDimension, 1.0f);
  EXPECT_EQ(engine_->QueryPlace("nope", query).status(),
            absl::NotFoundError(expected));
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("nope", 0);
  ASSERT_TRUE(events.ok());
  EXPECT_THAT(*events, IsEmpty());
  EXPECT_EQ(engine_->ReadEvents("bad fleet", 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(engine_->ListFleets(), IsEmpty());
}

TEST_F(MemoryEngineTest, DuplicatesAreCountedAndStoredOnce) {
  std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 5, rng_);
  MustUpload(traces);
  // A retry of the same upload.
  UploadResult retry = MustUpload(traces);
  EXPECT_EQ(retry.accepted, 0u);
  EXPECT_EQ(retry.duplicates, 5u);
  // Repeats inside one upload: the second copy of seq 7 is a duplicate, and
  // so is the already received seq 3.
  std::vector<core::MemoryTrace> batch = {
      MakeTrace("r1", 6, rng_), MakeTrace("r1", 7, rng_),
      MakeTrace("r1", 7, rng_), MakeTrace("r1", 3, rng_),
      MakeTrace("r2", 7, rng_)};
  UploadResult mixed = MustUpload(batch);
  EXPECT_EQ(mixed.accepted, 3u);
  EXPECT_EQ(mixed.duplicates, 2u);

  FleetStats stats = Stats();
  EXPECT_EQ(stats.pending_traces, 8u);
  const RobotStats* r1 = FindRobot(stats, "r1");
  ASSERT_NE(r1, nullptr);
  EXPECT_EQ(r1->received, 7u);
  EXPECT_EQ(r1->pending_traces, 7u);
  EXPECT_EQ(r1->max_seq, 7u);

  // Duplicates stay duplicates after consolidation.
  ASSERT_TRUE(engine_->Consolidate("f1").ok());
  UploadResult after = MustUpload(traces);
  EXPECT_EQ(after.duplicates, 5u);
  EXPECT_EQ(Stats().pending_traces, 0u);
}

TEST_F(MemoryEngineTest, BadInputIsRejectedAndChangesNothing) {
  MustUpload(MakeTraces("r1", 1, 5, rng_));
  const FleetStats before = Stats();

  struct Case {
    std::string name;
    std::string fleet_id;
    std::function<void(std::vector<core::MemoryTrace>&)> spoil;
    std::string message;
  };
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  const std::vector<Case> cases = {
      {"dimension", "f1",
       [](auto& t) { t[2].code.resize(kDimension * 2, 0.5f); },
       "traces[2].code has dimension 16 but fleet \"f1\" uses 8"},
      {"nan code", "f1", [&](auto& t) { t[2].code[1] = nan; }, "traces[2]"},
      {"inf place", "f1", [&](auto& t) { t[2].place.y = inf; }, "traces[2]"},
      {"inf reward", "f1", [&](auto& t) { t[2].reward = inf; }, "traces[2]"},
      {"negative reward", "f1", [](auto& t) { t[2].reward = -1.0f; },
       "traces[2]"},
      {"empty robot id", "f1", [](auto& t) { t[2].robot_id.clear(); },
       "traces[2].robot_id"},
      {"empty fleet id", "", [](auto&) {}, "fleet_id"},
      {"bad fleet id", "f 1", [](auto&) {}, "fleet_id"},
      {"encoder", "f1", [](auto& t) { t[2].encoder_version = "v2"; },
       "traces[2].encoder_version \"v2\" differs from fleet \"f1\"'s \"v1\""},
      {"oversized", "f1",
       [&](auto& t) {
         std::vector<core::MemoryTrace> more = MakeTraces("r3", 100, 51, rng_);
         t = std::move(more);
       },
       "at most 50"},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.name);
    std::vector<core::MemoryTrace> traces = MakeTraces("r2", 1, 4, rng_);
    c.spoil(traces);
    absl::StatusOr<UploadResult> result = engine_->Upload(c.fleet_id, traces);
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(result.status().message(), HasSubstr(c.message));
    ExpectSameStats(Stats(), before);
  }
  EXPECT_THAT(engine_->ListFleets(), ElementsAre("f1"));
}

TEST_F(MemoryEngineTest, NewFleetNeedsOneShapeInItsFirstUpload) {
  std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 4, rng_);
  traces[3].code.push_back(1.0f);
  absl::StatusOr<UploadResult> result = engine_->Upload("f2", traces);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              HasSubstr("traces[3].code has dimension 9 but traces[0]"));

  traces = MakeTraces("r1", 1, 4, rng_);
  traces[1].encoder_version = "v9";
  result = engine_->Upload("f2", traces);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(result.status().message(),
              HasSubstr("traces[1].encoder_version"));

  EXPECT_EQ(engine_->GetStats("f2").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_THAT(engine_->ListFleets(), IsEmpty());

  // An empty first upload creates nothing either.
  result = engine_->Upload("f2", {});
  ASSERT_TRUE(result.ok());
  EXPECT_EQ(result->accepted, 0u);
  EXPECT_THAT(engine_->ListFleets(), IsEmpty());
}

TEST_F(MemoryEngineTest, MemoryStaysWithinBoundsOverManySegments) {
  for (int segment = 0; segment < 12; ++segment) {
    const std::string robot = "r" + std::to_string(segment % 3);
    MustUpload(MakeTraces(robot, 1 + 20 * (segment / 3), 20, rng_));
    FleetStats stats = Stats();
    EXPECT_LE(stats.clusters, 5u);
    EXPECT_LE(stats.traces, 5u * 3u);
  }
  FleetStats stats = Stats();
  EXPECT_EQ(stats.consolidations, 12u);
  EXPECT_EQ(stats.clusters, 5u);
  EXPECT_EQ(stats.clusters_forgotten, 12u * 4u - 5u);
  EXPECT_EQ(stats.pending_traces, 0u);
  EXPECT_EQ(stats.last_event_id, 12u * 4u + stats.clusters_forgotten);

  std::map<uint64_t, int> per_cluster;
  std::vector<core::MemoryTrace> traces = AllTraces(*engine_, "f1", 200);
  EXPECT_EQ(traces.size(), stats.traces);
  for (const core::MemoryTrace& trace : traces) ++per_cluster[trace.cluster_id];
  EXPECT_EQ(per_cluster.size(), stats.clusters);
  for (const auto& [cluster_id, count] : per_cluster) EXPECT_LE(count, 3);
}

TEST_F(MemoryEngineTest, PerFleetMemoryOptionsReplaceTheServerWide) {
  core::MemoryOptions ablation = options_.memory;
  ablation.clustering = false;  // "w/o consolidation-clustering"
  ablation.max_clusters = 2;
  options_.fleet_memory["ablation"] = ablation;
  engine_ = OpenEngine();
  MustUpload(MakeTraces("r1", 1, 20, rng_), "ablation");
  MustUpload(MakeTraces("r1", 1, 20, rng_), "f1");
  FleetStats plain = Stats("ablation");
  EXPECT_EQ(plain.clusters, 1u);  // the whole segment, no k-means
  EXPECT_EQ(plain.traces, 20u);   // and no downsampling
  EXPECT_EQ(plain.max_clusters, 2u);
  FleetStats clustered = Stats("f1");
  EXPECT_EQ(clustered.max_clusters, 5u);
  EXPECT_LE(clustered.traces, 4u * 3u);

  options_.fleet_memory["bad"].replay_decay = 2.0;
  EXPECT_EQ(ValidateEngineOptions(options_).code(),
            absl::StatusCode::kInvalidArgument);
}

class ReplayTest : public MemoryEngineTest {
 protected:
  void SetUp() override {
    store_ = storage::NewInMemoryStore();
    options_ = SmallOptions();
    // Keep every trace (no downsampling, no forgetting) and no time decay,
    // so the weights are exactly the rewards.
    options_.memory.clusters_per_batch = 2;
    options_.memory.max_traces_per_cluster = 100;
    options_.memory.max_clusters = 100;
    options_.memory.replay_decay = 1.0;
    engine_ = OpenEngine();
    std::vector<core::MemoryTrace> traces;
    for (uint64_t seq = 1; seq <= 20; ++seq) {
      traces.push_back(MakeTrace("r1", seq, rng_, seq <= 10 ? 1.0f : 0.1f));
    }
    MustUpload(traces);
    EXPECT_EQ(Stats().traces, 20u);
  }
};

TEST_F(ReplayTest, FavoursHighRewards) {
  constexpr int kDraws = 2000;
  int high = 0;
  for (int i = 0; i < kDraws; ++i) {
    absl::StatusOr<std::vector<core::MemoryTrace>> drawn =
        engine_->SampleReplay("f1", "r1", 1);
    ASSERT_TRUE(drawn.ok()) << drawn.status();
    ASSERT_THAT(*drawn, SizeIs(1));
    if ((*drawn)[0].reward > 0.5f) ++high;
  }
  // P(high) = 10 / (10 + 10 * 0.1) = 0.91; uniform sampling would give 0.5.
  EXPECT_GT(high, kDraws * 8 / 10);
  EXPECT_LT(high, kDraws * 97 / 100);
  EXPECT_EQ(FindRobot(Stats(), "r1")->replayed, static_cast<uint64_t>(kDraws));
}

TEST_F(ReplayTest, IncrementsReplayCountsDurably) {
  absl::StatusOr<std::vector<core::MemoryTrace>> first =
      engine_->SampleReplay("f1", "r1", 100);
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_THAT(*first, SizeIs(20));  // fewer held than asked for
  absl::flat_hash_set<uint64_t> seqs;
  for (const core::MemoryTrace& trace : *first) {
    EXPECT_EQ(trace.replay_count, 1u);
    seqs.insert(trace.seq);
  }
  EXPECT_EQ(seqs.size(), 20u);  // without replacement

  absl::StatusOr<std::vector<core::MemoryTrace>> second =
      engine_->SampleReplay("f1", "peer", 20);
  ASSERT_TRUE(second.ok());
  for (const core::MemoryTrace& trace : *second) {
    EXPECT_EQ(trace.replay_count, 2u);
  }
  for (const core::MemoryTrace& trace : AllTraces(*engine_, "f1", 200)) {
    EXPECT_EQ(trace.replay_count, 2u);
  }
  FleetStats stats = Stats();
  EXPECT_EQ(FindRobot(stats, "r1")->replayed, 20u);
  // A robot that never uploaded gets a record.
  const RobotStats* peer = FindRobot(stats, "peer");
  ASSERT_NE(peer, nullptr);
  EXPECT_EQ(peer->replayed, 20u);
  EXPECT_EQ(peer->received, 0u);

  // Durable: a new engine over the same store sees the counts.
  engine_ = OpenEngine();
  for (const core::MemoryTrace& trace : AllTraces(*engine_, "f1", 200)) {
    EXPECT_EQ(trace.replay_count, 2u);
  }
  ExpectSameStats(Stats(), stats);
}

TEST_F(ReplayTest, RetryWithTheSameRequestIdIsCountedOnce) {
  absl::StatusOr<std::vector<core::MemoryTrace>> first =
      engine_->SampleReplay("f1", "r9", 5, "req-1");
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_EQ(first->size(), 5u);
  const FleetStats after_first = Stats();
  // The answer was lost; the robot retries with the same id.
  for (bool reopen : {false, true}) {
    if (reopen) engine_ = OpenEngine();
    absl::StatusOr<std::vector<core::MemoryTrace>> retry =
        engine_->SampleReplay("f1", "r9", 5, "req-1");
    ASSERT_TRUE(retry.ok()) << retry.status();
    ASSERT_EQ(retry->size(), 5u);
    for (size_t i = 0; i < 5; ++i) {
      EXPECT_EQ((*retry)[i].key(), (*first)[i].key());
      EXPECT_EQ((*retry)[i].replay_count, (*first)[i].replay_count);
    }
    ExpectSameStats(Stats(), after_first);
  }
  // A new id draws (and counts) again.
  ASSERT_TRUE(engine_->SampleReplay("f1", "r9", 5, "req-2").ok());
  EXPECT_EQ(FindRobot(Stats(), "r9")->replayed, 10u);
  EXPECT_EQ(engine_->SampleReplay("f1", "r9", 5, "bad id").status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(ReplayTest, RejectsBadCounts) {
  EXPECT_EQ(engine_->SampleReplay("f1", "r1", 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(engine_->SampleReplay("f1", "r1", 101).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(engine_->SampleReplay("f1", "", 1).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(FindRobot(Stats(), "r1")->replayed, 0u);
}

TEST_F(ReplayTest, StoredCodeFindsItselfFirst) {
  std::vector<core::MemoryTrace> traces = AllTraces(*engine_, "f1", 200);
  ASSERT_THAT(traces, SizeIs(20));
  for (const core::MemoryTrace& trace : traces) {
    PlaceQuery query;
    // Scaled: distances are between normalised codes.
    for (float value : trace.code) query.code.push_back(3.0f * value);
    query.k = 3;
    absl::StatusOr<std::vector<PlaceMatch>> matches =
        engine_->QueryPlace("f1", query);
    ASSERT_TRUE(matches.ok()) << matches.status();
    ASSERT_THAT(*matches, SizeIs(3));
    EXPECT_EQ((*matches)[0].trace.key(), trace.key());
    EXPECT_NEAR((*matches)[0].distance, 0.0f, 1e-3f);
    EXPECT_EQ((*matches)[0].trace.code, trace.code);
    EXPECT_LE((*matches)[0].distance, (*matches)[1].distance);
    EXPECT_LE((*matches)[1].distance, (*matches)[2].distance);
    EXPECT_LE((*matches)[2].distance, 2.0f);
  }
}

TEST_F(ReplayTest, QueryRejectsBadInput) {
  PlaceQuery query;
  query.code.assign(kDimension + 1, 1.0f);
  absl::StatusOr<std::vector<PlaceMatch>> matches =
      engine_->QueryPlace("f1", query);
  EXPECT_EQ(matches.status(),
            absl::InvalidArgumentError(
                "code has dimension 9 but fleet \"f1\" uses 8"));
  query.code.assign(kDimension, 1.0f);
  query.code[0] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_EQ(engine_->QueryPlace("f1", query).status().code(),
            absl::StatusCode::kInvalidArgument);
  query.code.assign(kDimension, 1.0f);
  query.k = 201;
  EXPECT_EQ(engine_->QueryPlace("f1", query).status().code(),
            absl::StatusCode::kInvalidArgument);
  query.k = 0;  // means 1
  matches = engine_->QueryPlace("f1", query);
  ASSERT_TRUE(matches.ok());
  EXPECT_THAT(*matches, SizeIs(1));
}

TEST_F(ReplayTest, PositionPriorKeepsOnlyNearbyTraces) {
  // Places are at x = 5 * seq. Query with the code of seq 1 but a prior
  // around seq 10 (x = 50) with 12 m radius: seqs 8..12 qualify.
  std::vector<core::MemoryTrace> traces = AllTraces(*engine_, "f1", 200);
  const core::MemoryTrace* first = nullptr;
  for (const core::MemoryTrace& trace : traces) {
    if (trace.seq == 1) first = &trace;
  }
  ASSERT_NE(first, nullptr);
  PlaceQuery query;
  query.code = first->code;
  query.k = 20;
  query.near = core::Place{50.0, 0.0, 0.0, 0.0};
  query.radius_m = 12.0;
  absl::StatusOr<std::vector<PlaceMatch>> matches =
      engine_->QueryPlace("f1", query);
  ASSERT_TRUE(matches.ok()) << matches.status();
  std::vector<uint64_t> seqs;
  for (const PlaceMatch& match : *matches) seqs.push_back(match.trace.seq);
  std::sort(seqs.begin(), seqs.end());
  EXPECT_THAT(seqs, ElementsAre(8, 9, 10, 11, 12));

  // Without the prior the trace finds itself.
  query.radius_m = 0.0;
  matches = engine_->QueryPlace("f1", query);
  ASSERT_TRUE(matches.ok());
  EXPECT_EQ((*matches)[0].trace.seq, 1u);
}

TEST_F(MemoryEngineTest, EventsHaveIncreasingIdsAndResumeAfterCursor) {
  for (int segment = 0; segment < 3; ++segment) {
    MustUpload(MakeTraces("r1", 1 + 20 * segment, 20, rng_));
  }
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok()) << events.status();
  const FleetStats stats = Stats();
  ASSERT_EQ(events->size(), stats.last_event_id);
  int added = 0;
  int forgotten = 0;
  for (size_t i = 0; i < events->size(); ++i) {
    const core::MemoryEvent& event = (*events)[i];
    EXPECT_EQ(event.id, i + 1);
    if (i > 0) {
      EXPECT_GE(event.timestamp_ns, (*events)[i - 1].timestamp_ns);
    }
    EXPECT_GT(event.timestamp_ns, 1000);  // from the injected clock
    EXPECT_NE(event.cluster_id, 0u);
    EXPECT_EQ(event.robot_id, "r1");
    if (event.type == core::EventType::kClusterAdded) {
      ++added;
      EXPECT_GE(event.trace_count, 1u);
      EXPECT_LE(event.trace_count, 3u);
    } else {
      ++forgotten;
    }
  }
  EXPECT_EQ(added, 12);
  EXPECT_EQ(forgotten, 7);
  EXPECT_EQ(static_cast<uint64_t>(forgotten), stats.clusters_forgotten);

  absl::StatusOr<std::vector<core::MemoryEvent>> rest =
      engine_->ReadEvents("f1", 5);
  ASSERT_TRUE(rest.ok());
  ASSERT_EQ(rest->size(), events->size() - 5);
  EXPECT_EQ(rest->front().id, 6u);
  EXPECT_EQ(rest->back().id, stats.last_event_id);
  rest = engine_->ReadEvents("f1", stats.last_event_id);
  ASSERT_TRUE(rest.ok());
  EXPECT_THAT(*rest, IsEmpty());
}

TEST_F(MemoryEngineTest, ReadEventsReturnsAtMostMaxEventsPerRead) {
  options_.max_events_per_read = 3;
  engine_ = OpenEngine();
  MustUpload(MakeTraces("r1", 1, 20, rng_));
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok());
  ASSERT_THAT(*events, SizeIs(3));
  events = engine_->ReadEvents("f1", events->back().id);
  ASSERT_TRUE(events.ok());
  ASSERT_THAT(*events, SizeIs(1));
  EXPECT_EQ((*events)[0].id, 4u);
}

TEST_F(MemoryEngineTest, EventRetentionKeepsTheNewestEvents) {
  options_.max_events_per_fleet = 5;
  engine_ = OpenEngine();
  for (int segment = 0; segment < 3; ++segment) {
    MustUpload(MakeTraces("r1", 1 + 20 * segment, 20, rng_));
  }
  const FleetStats stats = Stats();
  ASSERT_GT(stats.last_event_id, 5u);
  const uint64_t first = stats.first_event_id;
  EXPECT_GT(first, 1u);
  EXPECT_LE(stats.last_event_id - first + 1, 5u);
  // From the start: the oldest kept event first.
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok()) << events.status();
  ASSERT_FALSE(events->empty());
  EXPECT_EQ(events->front().id, first);
  EXPECT_EQ(events->back().id, stats.last_event_id);
  // A cursor right before the oldest kept event is fine; an older one was
  // compacted away.
  EXPECT_TRUE(engine_->ReadEvents("f1", first - 1).ok());
  const absl::Status gone = engine_->ReadEvents("f1", 1).status();
  EXPECT_EQ(gone.code(), absl::StatusCode::kOutOfRange);
  EXPECT_THAT(gone.message(), HasSubstr("retention"));
  // The bound survives a restart.
  engine_ = OpenEngine();
  EXPECT_EQ(Stats().first_event_id, first);
  EXPECT_EQ(engine_->ReadEvents("f1", 1).status().code(),
            absl::StatusCode::kOutOfRange);
}

TEST_F(MemoryEngineTest, QuotasRefuseUploadsAndChangeNothing) {
  double now = 0;
  options_.limits.robot_traces_per_second = 10;  // bucket of 20
  options_.limits.max_fleets = 1;
  options_.limits.max_traces_per_fleet = 25;
  options_.now_seconds = [&] { return now; };
  engine_ = OpenEngine();
  MustUpload(MakeTraces("r1", 1, 15, rng_));
  // Rate: 15 of 20 tokens spent.
  absl::StatusOr<UploadResult> refused =
      engine_->Upload("f1", MakeTraces("r1", 16, 10, rng_));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.status().message(), HasSubstr("robot_traces_per_second"));
  EXPECT_EQ(Stats().pending_traces + Stats().traces, 15u);
  // Stored traces: 15 held + 11 > 25.
  now = 10;
  refused = engine_->Upload("f1", MakeTraces("r2", 1, 11, rng_));
  EXPECT_THAT(refused.status().message(), HasSubstr("max_traces_per_fleet"));
  // Fleets: one exists.
  refused = engine_->Upload("f2", MakeTraces("r1", 1, 1, rng_));
  EXPECT_THAT(refused.status().message(), HasSubstr("max_fleets"));
  EXPECT_EQ(engine_->GetStats("f2").status().code(),
            absl::StatusCode::kNotFound);
  const FleetStats stats = Stats();
  EXPECT_EQ(stats.quota_rejections.at("robot_traces_per_second"), 1u);
  EXPECT_EQ(stats.quota_rejections.at("max_traces_per_fleet"), 1u);
  EXPECT_EQ(stats.robots.size(), 1u) << "a refused robot was recorded";
}

TEST_F(MemoryEngineTest, ReopeningRestoresTheSameMemory) {
  for (int segment = 0; segment < 6; ++segment) {
    const std::string robot = segment % 2 == 0 ? "r1" : "r2";
    MustUpload(MakeTraces(robot, 1 + 20 * (segment / 2), 20, rng_));
  }
  MustUpload(MakeTraces("r3", 1, 7, rng_));  // stays pending
  MustUpload(MakeTraces("r3", 1, 7, rng_), "f2");
  ASSERT_TRUE(engine_->SampleReplay("f1", "r1", 6).ok());
  ASSERT_TRUE(engine_->SampleReplay("f1", "r9", 4).ok());

  const FleetStats stats = Stats();
  std::vector<core::MemoryTrace> traces = AllTraces(*engine_, "f1", 200);
  std::vector<std::vector<PlaceMatch>> results;
  for (const core::MemoryTrace& trace : traces) {
    PlaceQuery query;
    query.code = trace.code;
    query.k = 4;
    absl::StatusOr<std::vector<PlaceMatch>> matches =
        engine_->QueryPlace("f1", query);
    ASSERT_TRUE(matches.ok());
    results.push_back(*std::move(matches));
  }
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok());

  engine_.reset();
  engine_ = OpenEngine();
  ASSERT_NE(engine_, nullptr);
  EXPECT_THAT(engine_->ListFleets(), ElementsAre("f1", "f2"));
  ExpectSameStats(Stats(), stats);
  EXPECT_EQ(Stats("f2").pending_traces, 7u);
  for (size_t i = 0; i < traces.size(); ++i) {
    PlaceQuery query;
    query.code = traces[i].code;
    query.k = 4;
    absl::StatusOr<std::vector<PlaceMatch>> matches =
        engine_->QueryPlace("f1", query);
    ASSERT_TRUE(matches.ok());
    ASSERT_EQ(matches->size(), results[i].size());
    for (size_t j = 0; j < matches->size(); ++j) {
      const core::MemoryTrace& a = (*matches)[j].trace;
      const core::MemoryTrace& b = results[i][j].trace;
      EXPECT_EQ(a.key(), b.key());
      EXPECT_EQ(a.replay_count, b.replay_count);
      EXPECT_EQ(a.cluster_id, b.cluster_id);
      EXPECT_EQ(a.code, b.code);
      EXPECT_EQ(a.domain, b.domain);
      EXPECT_FLOAT_EQ((*matches)[j].distance, results[i][j].distance);
    }
  }
  // Received sequence numbers survive: a retry is still a duplicate.
  UploadResult retry = MustUpload(MakeTraces("r1", 1, 20, rng_));
  EXPECT_EQ(retry.duplicates, 20u);
  // Event ids continue where they stopped.
  MustUpload(MakeTraces("r3", 8, 13, rng_));
  absl::StatusOr<std::vector<core::MemoryEvent>> more =
      engine_->ReadEvents("f1", stats.last_event_id);
  ASSERT_TRUE(more.ok());
  ASSERT_THAT(*more, ::testing::Not(IsEmpty()));
  EXPECT_EQ(more->front().id, stats.last_event_id + 1);
  EXPECT_EQ(events->size(), stats.last_event_id);
}

// From 10,000 traces a fleet's load fills (or loads) the index on a second
// thread while memory restores its clusters; every trace must come back
// under its key.
TEST_F(MemoryEngineTest, ReopeningALargeFleetFindsEveryTrace) {
  options_.memory.clusters_per_batch = 20;
  options_.memory.max_traces_per_cluster = 50;
  options_.memory.max_clusters = 5000;
  options_.segment_size = 200;
  options_.max_traces_per_upload = 200;
  options_.max_query_k = 20000;
  engine_ = OpenEngine();
  ASSERT_NE(engine_, nullptr);
  for (uint64_t first = 1; first <= 6000; first += 200) {
    MustUpload(MakeTraces("r1", first, 200, rng_));
    MustUpload(MakeTraces("r2", first, 200, rng_));
  }
  MustUpload(MakeTraces("r3", 1, 150, rng_));  // stays pending
  const FleetStats stats = Stats();
  ASSERT_GE(stats.traces + stats.pending_traces, 10000u);
  std::vector<core::MemoryTrace> traces = AllTraces(*engine_, "f1", 20000);
  ASSERT_EQ(traces.size(), stats.traces + stats.pending_traces);

  // Rebuilt after a crash, then loaded from the index snapshot of a clean
  // shutdown (the index on its second thread beside memory's restore).
  for (bool snapshot : {false, true}) {
    if (snapshot) ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
    engine_.reset();
    engine_ = OpenEngine();
    ASSERT_NE(engine_, nullptr);
    ExpectSameStats(Stats(), stats);
    EXPECT_EQ(AllTraces(*engine_, "f1", 20000).size(), traces.size());
    for (size_t i = 0; i < traces.size(); i += 37) {
      PlaceQuery query;
      query.code = traces[i].code;
      query.k = 1;
      absl::StatusOr<std::vector<PlaceMatch>> matches =
          engine_->QueryPlace("f1", query);
      ASSERT_TRUE(matches.ok()) << matches.status();
      ASSERT_EQ(matches->size(), 1u);
      EXPECT_EQ(matches->front().trace.key(), traces[i].key());
      EXPECT_EQ(matches->front().trace.code, traces[i].code);
      EXPECT_EQ(matches->front().distance, 0.0f);
    }
  }
}

// Forwards to a tiered index and counts the Loads that succeed.
class CountingIndex : public ForwardingIndex {
 public:
  CountingIndex(size_t dimension, std::atomic<int>* loads)
      : ForwardingIndex(index::NewTieredIndex(dimension, Options())),
        loads_(loads) {}
  static index::TieredIndexOptions Options() {
    index::TieredIndexOptions options;
    options.hnsw_from = 300;
    options.background = false;  // the same calls give the same graph
    return options;
  }
  absl::Status Load(core::ByteReader& in) override {
    absl::Status status = inner_->Load(in);
    if (status.ok()) ++*loads_;
    return status;
  }

 private:
  std::atomic<int>* loads_;
};

class IndexSnapshotTest : public MemoryEngineTest {
 protected:
  void SetUp() override {
    MemoryEngineTest::SetUp();
    options_.memory.clusters_per_batch = 10;
    options_.memory.max_traces_per_cluster = 20;
    options_.memory.max_clusters = 60;
    options_.memory.forgetting_exact_below = 16;  // the centroid graph too
    options_.segment_size = 100;
    options_.max_traces_per_upload = 100;
    options_.max_query_k = 5000;
    engine_ = Open();
    ASSERT_NE(engine_, nullptr);
  }

  std::unique_ptr<MemoryEngine> Open(PlaceIndexFactory factory = nullptr,
                                     MemoryStore* store = nullptr) {
    engine_.reset();
    if (!factory) {
      factory = [this](size_t dimension) {
        return std::make_unique<CountingIndex>(dimension, &loads_);
      };
    }
    EngineHooks hooks;
    hooks.on_index_snapshot = [this](std::string_view, double) { ++saves_; };
    absl::StatusOr<std::unique_ptr<MemoryEngine>> engine = MemoryEngine::Open(
        options_, store != nullptr ? store : store_.get(), factory, hooks);
    EXPECT_TRUE(engine.ok()) << engine.status();
    return engine.ok() ? *std::move(engine) : nullptr;
  }

  // Uploads `robot`'s traces first..last in messages of 100 (a segment).
  void UploadSegments(const std::string& robot, uint64_t first, uint64_t last) {
    for (; first <= last; first += 100) {
      MustUpload(MakeTraces(robot, first, 100, rng_));
    }
  }

  // Every trace's nearest match is itself, at distance 0.
  void ExpectEveryTraceFindsItself() {
    const std::vector<core::MemoryTrace> traces =
        AllTraces(*engine_, "f1", 5000);
    ASSERT_FALSE(traces.empty());
    const FleetStats stats = Stats();
    EXPECT_EQ(traces.size(), stats.traces + stats.pending_traces);
    ExpectEachTraceFindsItself(*engine_, traces);
  }

  // The five nearest keys to each of `queries`.
  std::vector<std::vector<core::TraceKey>> Nearest(
      const std::vector<core::MemoryTrace>& queries) {
    std::vector<std::vector<core::TraceKey>> nearest;
    for (const core::MemoryTrace& trace : queries) {
      PlaceQuery query;
      query.code = trace.code;
      query.k = 5;
      absl::StatusOr<std::vector<PlaceMatch>> matches =
          engine_->QueryPlace("f1", query);
      EXPECT_TRUE(matches.ok()) << matches.status();
      nearest.emplace_back();
      if (!matches.ok()) continue;
      for (const PlaceMatch& match : *matches) {
        nearest.back().push_back(match.trace.key());
      }
    }
    return nearest;
  }

  // Every key in `nearest` is one of the fleet's traces now.
  void ExpectOnlyHeldKeys(
      const std::vector<std::vector<core::TraceKey>>& nearest) {
    std::set<core::TraceKey> held;
    for (const core::MemoryTrace& trace : AllTraces(*engine_, "f1", 5000)) {
      held.insert(trace.key());
    }
    for (const auto& keys : nearest) {
      for (const core::TraceKey& key : keys) {
        EXPECT_TRUE(held.contains(key)) << key.robot_id << " " << key.seq;
      }
    }
  }

  std::atomic<int> loads_{0};
  std::atomic<int> saves_{0};
};

TEST_F(IndexSnapshotTest, CleanShutdownSkipsTheRebuildAndKeepsEveryHandle) {
  for (uint64_t first = 1; first <= 900; first += 100) {
    MustUpload(MakeTraces("r1", first, 100, rng_));
    MustUpload(MakeTraces("r2", first, 100, rng_));
  }
  MustUpload(MakeTraces("r3", 1, 70, rng_));  // stays pending
  const FleetStats stats = Stats();
  ASSERT_GT(stats.clusters_forgotten, 0u);  // handles were removed too
  const std::vector<core::MemoryTrace> queries = MakeTraces("q", 1, 30, rng_);
  const auto before = Nearest(queries);

  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  engine_ = Open();
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(loads_.load(), 1);
  ExpectSameStats(Stats(), stats);
  EXPECT_EQ(Nearest(queries), before);  // the same graph
  ExpectEveryTraceFindsItself();

  // Consolidation and forgetting reach the loaded index through the loaded
  // handles.
  UploadSegments("r1", 901, 1300);
  MustUpload(MakeTraces("r3", 71, 30, rng_));
  ASSERT_GT(Stats().clusters_forgotten, stats.clusters_forgotten);
  ExpectEveryTraceFindsItself();

  // The snapshot is kept: a restart after a crash loads it again and
  // reconciles it with what was stored since (uploads, consolidations,
  // forgetting).
  const FleetStats later = Stats();
  engine_ = Open();
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(loads_.load(), 2);
  ExpectSameStats(Stats(), later);
  ExpectEveryTraceFindsItself();
  ExpectOnlyHeldKeys(Nearest(queries));
}

// A snapshot of another kind of index: memory takes its part (the
// centroids), the index is rebuilt from the restored memory's traces.
TEST_F(IndexSnapshotTest, IndexOfAnotherKindIsRebuiltBesideTheRestoredMemory) {
  UploadSegments("r1", 1, 600);
  MustUpload(MakeTraces("r2", 1, 30, rng_));  // pending
  const FleetStats stats = Stats();
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  engine_ = Open(ExactFactory());
  ASSERT_NE(engine_, nullptr);
  ExpectSameStats(Stats(), stats);
  ExpectEveryTraceFindsItself();
  MustUpload(MakeTraces("r1", 601, 100, rng_));  // forgetting goes on
  MustUpload(MakeTraces("r1", 701, 100, rng_));
  EXPECT_GT(Stats().clusters_forgotten, stats.clusters_forgotten);
  ExpectEveryTraceFindsItself();
}

// A periodic snapshot while serving, then uploads that add, consolidate
// and forget, then a crash: the next start loads the snapshot and
// reconciles it (adds what is new, removes what was forgotten) instead of
// rebuilding: every trace finds itself, no answer names a forgotten trace,
// and forgetting goes on.
TEST_F(IndexSnapshotTest, CrashAfterAPeriodicSnapshotReconcilesIt) {
  UploadSegments("r1", 1, 400);
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  ASSERT_EQ(saves_.load(), 1);
  const uint64_t forgotten = Stats().clusters_forgotten;
  for (uint64_t first = 401; first <= 900; first += 100) {
    MustUpload(MakeTraces("r1", first, 100, rng_));
    MustUpload(MakeTraces("r2", first, 100, rng_));
  }
  MustUpload(MakeTraces("r3", 1, 40, rng_));  // pending
  const FleetStats stats = Stats();
  ASSERT_GT(stats.clusters_forgotten, forgotten);  // handles to remove
  const std::vector<core::MemoryTrace> queries = MakeTraces("q", 1, 30, rng_);

  engine_ = Open();  // no snapshot at the end: a crash
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(loads_.load(), 1);
  ExpectSameStats(Stats(), stats);
  ExpectEveryTraceFindsItself();
  const auto reconciled = Nearest(queries);
  ExpectOnlyHeldKeys(reconciled);
  // Consolidation and forgetting go on from the reconciled state.
  MustUpload(MakeTraces("r1", 901, 100, rng_));
  MustUpload(MakeTraces("r2", 901, 100, rng_));
  EXPECT_GT(Stats().clusters_forgotten, stats.clusters_forgotten);
  ExpectEveryTraceFindsItself();
}

// Periodic snapshots skip fleets that did not change since their last one
// (a snapshot loaded unchanged counts as one) and fleets below min_codes.
TEST_F(IndexSnapshotTest, PeriodicSnapshotsSkipUnchangedAndSmallFleets) {
  UploadSegments("r1", 1, 300);
  const size_t codes = Stats().traces + Stats().pending_traces;
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.min_codes = codes + 1}).ok());
  EXPECT_EQ(saves_.load(), 0);
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.min_codes = codes}).ok());
  EXPECT_EQ(saves_.load(), 1);
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_EQ(saves_.load(), 1);
  // A sample changes replay counts only, which no snapshot holds.
  ASSERT_TRUE(engine_->SampleReplay("f1", "r1", 10).ok());
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_EQ(saves_.load(), 1);
  MustUpload(MakeTraces("r2", 1, 10, rng_));
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_EQ(saves_.load(), 2);
  // Loaded unchanged: the file on disk is the state, nothing to write.
  saves_ = 0;
  engine_ = Open();
  ASSERT_NE(engine_, nullptr);
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_EQ(saves_.load(), 0);
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  EXPECT_EQ(saves_.load(), 1);
}

// A snapshot whose codes differ from the store's under the same keys (the
// fleet of another server's history) is refused and the index rebuilt.
TEST_F(IndexSnapshotTest, SnapshotOfAnotherHistoryIsRebuilt) {
  UploadSegments("r1", 1, 400);
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  std::vector<char> bytes;
  ASSERT_TRUE(store_
                  ->ReadIndexSnapshot("f1",
                                      [&bytes](std::span<const char> read) {
                                        bytes.assign(read.begin(), read.end());
                                        return absl::OkStatus();
                                      })
                  .ok());
  // The same keys with other codes, in another store, with the snapshot.
  std::unique_ptr<MemoryStore> other = storage::NewInMemoryStore();
  engine_ = Open(nullptr, other.get());
  ASSERT_NE(engine_, nullptr);
  UploadSegments("r1", 1, 400);
  engine_.reset();
  ASSERT_TRUE(other
                  ->SaveIndexSnapshot("f1",
                                      [&bytes](core::ByteWriter& out) {
                                        out.PutBytes(bytes.data(),
                                                     bytes.size());
                                        return absl::OkStatus();
                                      })
                  .ok());
  engine_ = Open(nullptr, other.get());
  ASSERT_NE(engine_, nullptr);
  ExpectEveryTraceFindsItself();
  engine_.reset();
}

// The server's periodic snapshots run beside the fleet's uploads, samples
// and queries: each snapshot is of one consistent state (uploads wait,
// queries do not), and after a crash the last one loads and is reconciled
// with everything stored after it. Run under ThreadSanitizer too.
TEST_F(MemoryEngineTest, SnapshotsBesideUploadsAndQueriesReloadAfterACrash) {
  MustUpload(MakeTraces("r0", 1, 20, rng_));  // the fleet exists
  std::atomic<bool> uploading{true};
  std::atomic<int> snapshots{0};
  std::vector<std::thread> threads;
  for (int robot = 1; robot <= 2; ++robot) {
    threads.emplace_back([this, robot] {
      std::mt19937_64 rng(robot);
      const std::string robot_id = absl::StrCat("r", robot);
      for (uint64_t first = 1; first <= 400; first += 25) {
        absl::StatusOr<UploadResult> result =
            engine_->Upload("f1", MakeTraces(robot_id, first, 25, rng));
        EXPECT_TRUE(result.ok()) << result.status();
      }
      if (robot == 1) {
        EXPECT_TRUE(engine_->SampleReplay("f1", robot_id, 5).ok());
      }
    });
  }
  threads.emplace_back([this, &uploading] {
    std::mt19937_64 rng(9);
    do {
      PlaceQuery query;
      query.code = MakeTraces("q", 1, 1, rng)[0].code;
      query.k = 3;
      EXPECT_TRUE(engine_->QueryPlace("f1", query).ok());
    } while (uploading);
  });
  threads.emplace_back([this, &uploading, &snapshots] {
    do {
      EXPECT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
      ++snapshots;
    } while (uploading);
  });
  threads[0].join();
  threads[1].join();
  uploading = false;
  threads[2].join();
  threads[3].join();
  EXPECT_GT(snapshots.load(), 0);
  // The last state, then one more upload after the last snapshot.
  MustUpload(MakeTraces("r3", 1, 30, rng_));
  const FleetStats stats = Stats();
  const std::vector<core::MemoryTrace> traces = AllTraces(*engine_, "f1", 200);
  ASSERT_EQ(traces.size(), stats.traces + stats.pending_traces);

  engine_ = OpenEngine();  // a crash: no snapshot at the end
  ASSERT_NE(engine_, nullptr);
  ExpectSameStats(Stats(), stats);
  EXPECT_EQ(AllTraces(*engine_, "f1", 200).size(), traces.size());
  ExpectEachTraceFindsItself(*engine_, traces);
}

// A snapshot's file is synced after the fleet's locks are released: an
// upload and a query made while it syncs complete, and the snapshot still
// loads (it holds the state before that upload, which the load adds).
TEST_F(MemoryEngineTest, UploadsGoOnWhileASnapshotSyncs) {
  MustUpload(MakeTraces("r1", 1, 20, rng_));
  const std::vector<core::MemoryTrace> later = MakeTraces("r2", 1, 15, rng_);
  SlowSyncStore slow(store_.get(), [this, &later] {
    absl::StatusOr<UploadResult> uploaded = engine_->Upload("f1", later);
    EXPECT_TRUE(uploaded.ok()) << uploaded.status();
    PlaceQuery query;
    query.code = later[0].code;
    EXPECT_TRUE(engine_->QueryPlace("f1", query).ok());
  });
  engine_.reset();
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options_, &slow, ExactFactory());
  ASSERT_TRUE(opened.ok()) << opened.status();
  engine_ = *std::move(opened);
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  const FleetStats stats = Stats();
  EXPECT_EQ(stats.pending_traces, 15u);  // r2's upload went in meanwhile
  // The next snapshot is due: the upload came after the last one's write.
  int saved = 0;
  engine_.reset();
  EngineHooks hooks;
  hooks.on_index_snapshot = [&saved](std::string_view, double) { ++saved; };
  engine_ = OpenEngine(hooks);
  ASSERT_NE(engine_, nullptr);
  ExpectSameStats(Stats(), stats);
  PlaceQuery query;
  query.code = later[3].code;
  absl::StatusOr<std::vector<PlaceMatch>> matches =
      engine_->QueryPlace("f1", query);
  ASSERT_TRUE(matches.ok()) << matches.status();
  ASSERT_FALSE(matches->empty());
  EXPECT_EQ(matches->front().trace.key(), later[3].key());
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_EQ(saved, 1);  // the load added r2's traces: changed
}

TEST_F(MemoryEngineTest, ListenersFireAfterEventsAreDurable) {
  std::vector<uint64_t> f1_calls;
  std::vector<uint64_t> f2_calls;
  uint64_t durable_at_call = 0;
  const uint64_t h1 = engine_->Subscribe("f1", [&](uint64_t last) {
    f1_calls.push_back(last);
    // Outside the fleet lock and after the events are durable.
    absl::StatusOr<std::vector<core::MemoryEvent>> events =
        engine_->ReadEvents("f1", 0);
    if (events.ok() && !events->empty()) durable_at_call = events->back().id;
  });
  engine_->Subscribe("f2", [&](uint64_t last) { f2_calls.push_back(last); });

  MustUpload(MakeTraces("r1", 1, 10, rng_));
  EXPECT_THAT(f1_calls, IsEmpty());  // no events yet
  MustUpload(MakeTraces("r1", 11, 10, rng_));
  const uint64_t last = Stats().last_event_id;
  EXPECT_THAT(f1_calls, ElementsAre(last));
  EXPECT_EQ(durable_at_call, last);
  EXPECT_THAT(f2_calls, IsEmpty());

  engine_->Unsubscribe(h1);
  MustUpload(MakeTraces("r1", 21, 20, rng_));
  EXPECT_THAT(f1_calls, SizeIs(1));
}

TEST_F(MemoryEngineTest, HooksSeeUploadsConsolidationsSamplesAndQueries) {
  int uploads = 0;
  int consolidations = 0;
  uint64_t consolidated_traces = 0;
  size_t sampled = 0;
  int queries = 0;
  EngineHooks hooks;
  hooks.on_upload = [&](std::string_view fleet, const UploadResult& result) {
    EXPECT_EQ(fleet, "f1");
    ++uploads;
  };
  hooks.on_consolidate = [&](std::string_view, const ConsolidateResult& result,
                             double seconds) {
    EXPECT_GE(seconds, 0.0);
    ++consolidations;
    consolidated_traces += result.consolidated_traces;
  };
  hooks.on_sample = [&](std::string_view, size_t count) { sampled += count; };
  hooks.on_query = [&](std::string_view, double) { ++queries; };
  engine_ = OpenEngine(hooks);
  MustUpload(MakeTraces("r1", 1, 20, rng_));
  MustUpload(MakeTraces("r2", 1, 3, rng_));
  ASSERT_TRUE(engine_->Consolidate("f1").ok());
  ASSERT_TRUE(engine_->SampleReplay("f1", "r1", 2).ok());
  AllTraces(*engine_, "f1", 10);
  EXPECT_EQ(uploads, 2);
  EXPECT_EQ(consolidations, 2);
  EXPECT_EQ(consolidated_traces, 23u);
  EXPECT_EQ(sampled, 2u);
  EXPECT_EQ(queries, 1);
}

TEST_F(MemoryEngineTest, ServerFieldsOfUploadsAreIgnored) {
  std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 20, rng_);
  for (core::MemoryTrace& trace : traces) {
    trace.replay_count = 7;
    trace.cluster_id = 99;
  }
  options_.memory.max_traces_per_cluster = 100;
  engine_ = OpenEngine();
  MustUpload(traces);
  std::vector<core::MemoryTrace> stored = AllTraces(*engine_, "f1", 200);
  ASSERT_THAT(stored, SizeIs(20));
  absl::flat_hash_set<uint64_t> clusters;
  for (const core::MemoryTrace& trace : stored) {
    EXPECT_EQ(trace.replay_count, 0u);
    clusters.insert(trace.cluster_id);
    const core::MemoryTrace& sent = traces[trace.seq - 1];
    EXPECT_EQ(trace.code, sent.code);
    EXPECT_EQ(trace.domain, sent.domain);
    EXPECT_EQ(trace.place.x, sent.place.x);
    EXPECT_EQ(trace.reward, sent.reward);
    EXPECT_EQ(trace.timestamp_ns, sent.timestamp_ns);
    EXPECT_EQ(trace.encoder_version, "v1");
  }
  EXPECT_THAT(clusters, ::testing::UnorderedElementsAre(1, 2, 3, 4));
}

TEST_F(MemoryEngineTest, ConcurrentCallsOnSeveralFleets) {
  constexpr int kThreads = 4;
  constexpr int kSegments = 3;
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([this, t] {
      std::mt19937_64 rng(100 + t);
      const std::string own = "fleet" + std::to_string(t);
      const std::string robot = "r" + std::to_string(t);
      for (int segment = 0; segment < kSegments; ++segment) {
        std::vector<core::MemoryTrace> traces =
            MakeTraces(robot, 1 + 20 * segment, 20, rng);
        EXPECT_TRUE(engine_->Upload(own, traces).ok());
        EXPECT_TRUE(engine_->Upload("shared", traces).ok());
        EXPECT_TRUE(engine_->GetStats("shared").ok());
        PlaceQuery query;
        query.code = traces[0].code;
        query.k = 5;
        EXPECT_TRUE(engine_->QueryPlace(own, query).ok());
        EXPECT_TRUE(engine_->SampleReplay("shared", robot, 3).ok());
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  EXPECT_THAT(engine_->ListFleets(), SizeIs(kThreads + 1));
  FleetStats shared = Stats("shared");
  EXPECT_EQ(shared.consolidations, static_cast<uint64_t>(kThreads * kSegments));
  EXPECT_EQ(shared.clusters, 5u);
  EXPECT_THAT(shared.robots, SizeIs(kThreads));
  for (const RobotStats& robot : shared.robots) {
    EXPECT_EQ(robot.received, 20u * kSegments);
    EXPECT_EQ(robot.replayed, 3u * kSegments);
  }
  ExpectEventIds1To(*engine_, "shared", shared.last_event_id);
}

// Uploads of one robot racing each other: plans made ahead go stale (a
// segment another upload filled first) and are made again under the lock;
// every trace is received once and every segment consolidated once.
TEST_F(MemoryEngineTest, RacingUploadsOfOneRobotConsolidateEachSegmentOnce) {
  constexpr int kThreads = 4;
  std::mt19937_64 rng(31);
  const std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 60, rng);
  std::vector<std::thread> threads;
  for (int t = 0; t < kThreads; ++t) {
    threads.emplace_back([this, t, &traces] {
      for (int i = 0; i < 3; ++i) {
        const size_t segment = static_cast<size_t>((i + t) % 3);
        EXPECT_TRUE(
            engine_->Upload("f1", std::span(traces).subspan(20 * segment, 20))
                .ok());
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  const FleetStats stats = Stats();
  EXPECT_EQ(stats.consolidations, 3u);
  EXPECT_EQ(stats.pending_traces, 0u);
  ASSERT_THAT(stats.robots, SizeIs(1));
  EXPECT_EQ(stats.robots[0].received, 60u);
  ExpectEventIds1To(*engine_, "f1", stats.last_event_id);
}

// Queries and stats run while an upload's or a sample's store write is in
// flight (they do not wait for its fsync); a second upload waits for the
// first, so writes reach the store in order; the blocked upload's traces
// are not visible before they are durable.
TEST_F(MemoryEngineTest, ReadersDoNotWaitForStoreWrites) {
  GatedStore gated(store_.get());
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options_, &gated, ExactFactory());
  ASSERT_TRUE(opened.ok()) << opened.status();
  MemoryEngine& engine = **opened;
  ASSERT_TRUE(engine.Upload("f1", MakeTraces("r1", 1, 10, rng_)).ok());
  ASSERT_TRUE(engine.Consolidate("f1").ok());
  const std::vector<core::MemoryTrace> held = MakeTraces("r2", 1, 5, rng_);

  gated.Hold();
  std::thread sampler(
      [&] { EXPECT_TRUE(engine.SampleReplay("f1", "r1", 3).ok()); });
  std::thread uploader([&] { EXPECT_TRUE(engine.Upload("f1", held).ok()); });
  gated.AwaitWaiting(1);
  // One write waits in the store, the other writer behind it; readers run.
  for (int i = 0; i < 5; ++i) {
    absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
    ASSERT_TRUE(stats.ok()) << stats.status();
    EXPECT_EQ(stats->pending_traces, 0u);  // r2's upload is not durable yet
    PlaceQuery query;
    query.code = held[0].code;
    query.k = 3;
    absl::StatusOr<std::vector<PlaceMatch>> found =
        engine.QueryPlace("f1", query);
    ASSERT_TRUE(found.ok()) << found.status();
    for (const PlaceMatch& match : *found)
      EXPECT_NE(match.trace.robot_id, "r2");
  }
  gated.Release();
  sampler.join();
  uploader.join();
  absl::StatusOr<FleetStats> after = engine.GetStats("f1");
  ASSERT_TRUE(after.ok()) << after.status();
  const FleetStats& stats = *after;
  ASSERT_NE(FindRobot(stats, "r2"), nullptr);
  EXPECT_EQ(FindRobot(stats, "r2")->pending_traces, 5u);
  EXPECT_EQ(FindRobot(stats, "r1")->replayed, 3u);
  // And the store agrees after a reopen.
  absl::StatusOr<std::unique_ptr<MemoryEngine>> reopened =
      MemoryEngine::Open(options_, store_.get(), ExactFactory());
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  absl::StatusOr<FleetStats> again = (*reopened)->GetStats("f1");
  ASSERT_TRUE(again.ok()) << again.status();
  ExpectSameStats(stats, *again);
}

// GetStats reports the place index's backlog: with the tiered index, whose
// graph fills in the background, the codes not yet in the graph, until the
// background thread has moved them all; with the exact index, none.
TEST_F(MemoryEngineTest, StatsReportTheIndexBacklog) {
  std::unique_ptr<MemoryStore> store = storage::NewInMemoryStore();
  EngineOptions options = SmallOptions();
  options.segment_size = 1000;  // everything stays pending (and indexed)
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options, store.get(), [](size_t dimension) {
        index::TieredIndexOptions tiered;
        tiered.hnsw_from = 10;
        return index::NewTieredIndex(dimension, tiered);
      });
  ASSERT_TRUE(opened.ok()) << opened.status();
  MemoryEngine& engine = **opened;
  for (uint64_t first = 1; first <= 150; first += 50) {
    ASSERT_TRUE(engine.Upload("f1", MakeTraces("r1", first, 50, rng_)).ok());
  }
  absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->pending_traces, 150u);
  EXPECT_LE(stats->unindexed_codes, 150u);
  const absl::Time deadline = absl::Now() + absl::Seconds(60);
  while (stats->unindexed_codes > 0 && absl::Now() < deadline) {
    absl::SleepFor(absl::Milliseconds(10));
    stats = engine.GetStats("f1");
    ASSERT_TRUE(stats.ok()) << stats.status();
  }
  EXPECT_EQ(stats->unindexed_codes, 0u);
  MustUpload(MakeTraces("r1", 1, 30, rng_));
  EXPECT_EQ(Stats().unindexed_codes, 0u);
}

TEST_F(MemoryEngineTest, StoreFailureDuringUploadStoresNothing) {
  FlakyStore flaky(store_.get());
  flaky.fail_after = 0;
  absl::StatusOr<std::unique_ptr<MemoryEngine>> engine =
      MemoryEngine::Open(options_, &flaky, ExactFactory());
  ASSERT_TRUE(engine.ok());
  absl::StatusOr<UploadResult> result =
      (*engine)->Upload("f1", MakeTraces("r1", 1, 5, rng_));
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInternal);
  EXPECT_THAT((*engine)->ListFleets(), IsEmpty());
  flaky.fail_after = -1;
  result = (*engine)->Upload("f1", MakeTraces("r1", 1, 5, rng_));
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 5u);
}

// An upload that fills a segment is stored together with the segment's
// consolidation, in one write: when that write fails, nothing of the upload
// is stored and the fleet is as before it.
TEST_F(MemoryEngineTest, StoreFailureOfAConsolidatingUploadStoresNothing) {
  FlakyStore flaky(store_.get());
  std::unique_ptr<MemoryEngine> opened = OpenOn(options_, &flaky);
  ASSERT_NE(opened, nullptr);
  MemoryEngine& engine = *opened;
  std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 20, rng_);
  const std::vector<core::MemoryTrace> first(traces.begin(),
                                             traces.begin() + 5);
  const std::vector<core::MemoryTrace> rest(traces.begin() + 5, traces.end());
  ASSERT_TRUE(engine.Upload("f1", first).ok());
  flaky.fail_after = flaky.applies;
  absl::StatusOr<UploadResult> result = engine.Upload("f1", rest);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInternal);
  EXPECT_EQ(flaky.applies, flaky.fail_after + 1);  // one write was tried

  // Memory was reloaded from the store: the first 5 traces, pending.
  absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->pending_traces, 5u);
  EXPECT_EQ(stats->traces, 0u);
  EXPECT_EQ(stats->clusters, 0u);
  EXPECT_EQ(stats->last_event_id, 0u);

  // The retry is no duplicate: it is stored and consolidated.
  flaky.fail_after = -1;
  result = engine.Upload("f1", rest);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 15u);
  EXPECT_EQ(result->duplicates, 0u);
  EXPECT_EQ(result->consolidations, 1u);
  stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->pending_traces, 0u);
  EXPECT_EQ(stats->clusters, 4u);
  EXPECT_EQ(stats->last_event_id, 4u);
}

// The write of an upload that fills a segment: one store write for the
// upload and its consolidation; the other robots' traces of the same upload
// stay pending; after a reopen everything is where it was.
TEST_F(MemoryEngineTest, AnUploadThatFillsASegmentIsOneWrite) {
  FlakyStore counting(store_.get());
  std::unique_ptr<MemoryEngine> opened = OpenOn(options_, &counting);
  ASSERT_NE(opened, nullptr);
  MemoryEngine& engine = *opened;
  ASSERT_TRUE(engine.Upload("f1", MakeTraces("r1", 1, 12, rng_)).ok());
  const int before = counting.applies;
  // r1 fills its segment (12 + 8 = 20); r2's 6 traces stay pending.
  std::vector<core::MemoryTrace> mixed = MakeTraces("r1", 13, 8, rng_);
  for (core::MemoryTrace& trace : MakeTraces("r2", 1, 6, rng_)) {
    mixed.push_back(std::move(trace));
  }
  absl::StatusOr<UploadResult> result = engine.Upload("f1", mixed);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->accepted, 14u);
  EXPECT_EQ(result->consolidations, 1u);
  EXPECT_EQ(counting.applies, before + 1);
  absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->pending_traces, 6u);
  EXPECT_EQ(stats->clusters, 4u);

  // Two robots filling their segments at once: both consolidate.
  std::vector<core::MemoryTrace> both = MakeTraces("r2", 7, 14, rng_);
  for (core::MemoryTrace& trace : MakeTraces("r3", 1, 20, rng_)) {
    both.push_back(std::move(trace));
  }
  result = engine.Upload("f1", both);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->consolidations, 2u);

  stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok());
  const std::vector<core::MemoryTrace> traces = AllTraces(engine, "f1", 200);
  opened.reset();
  engine_.reset();
  engine_ = OpenEngine();
  ASSERT_NE(engine_, nullptr);
  ExpectSameStats(Stats(), *stats);
  EXPECT_EQ(Stats().pending_traces, 0u);
  const std::vector<core::MemoryTrace> reopened =
      AllTraces(*engine_, "f1", 200);
  ASSERT_EQ(reopened.size(), traces.size());
  for (size_t i = 0; i < traces.size(); ++i) {
    EXPECT_EQ(reopened[i].key(), traces[i].key());
    EXPECT_EQ(reopened[i].cluster_id, traces[i].cluster_id);
    EXPECT_EQ(reopened[i].code, traces[i].code);
  }
  // Every received sequence number survived: retries are duplicates.
  result = engine_->Upload("f1", mixed);
  ASSERT_TRUE(result.ok());
  EXPECT_EQ(result->duplicates, 14u);
}

// A segment's k-means has a seed of its own (the fleet's, the robot's, the
// segment's first seq): it clusters the same whether it was planned ahead
// of the fleet's lock (an upload that fills it), in an explicit Consolidate,
// or after other robots' segments.
TEST(SegmentPlanTest, ASegmentClustersTheSameHoweverItIsConsolidated) {
  EngineOptions options = SmallOptions();
  options.memory.max_clusters = 100;  // nothing forgotten
  std::mt19937_64 data(17);
  std::vector<core::MemoryTrace> r1 = MakeTraces("r1", 1, 20, data);
  for (size_t i = 0; i < r1.size(); ++i) r1[i].reward = 0.1f * (i % 7);
  const std::vector<core::MemoryTrace> r2 = MakeTraces("r2", 1, 20, data);
  // Per cluster of r1's segment, the seqs it kept.
  auto membership = [](const MemoryEngine& engine) {
    std::vector<std::vector<uint64_t>> clusters;
    absl::StatusOr<ClusterListing> listing = engine.ListClusters("f1", true);
    EXPECT_TRUE(listing.ok()) << listing.status();
    if (!listing.ok()) return clusters;
    for (const ClusterSummary& cluster : listing->clusters) {
      if (cluster.robot_id != "r1") continue;
      std::vector<uint64_t> seqs;
      for (const TracePlace& place : cluster.places) seqs.push_back(place.seq);
      std::sort(seqs.begin(), seqs.end());
      clusters.push_back(std::move(seqs));
    }
    std::sort(clusters.begin(), clusters.end());
    return clusters;
  };
  std::unique_ptr<MemoryStore> store_a = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> a = OpenOn(options, store_a.get());
  ASSERT_NE(a, nullptr);
  ASSERT_TRUE(a->Upload("f1", r1).ok());

  std::unique_ptr<MemoryStore> store_b = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> b = OpenOn(options, store_b.get());
  ASSERT_NE(b, nullptr);
  ASSERT_TRUE(b->Upload("f1", r2).ok());
  ASSERT_TRUE(b->Upload("f1", std::span(r1).first(10)).ok());
  ASSERT_TRUE(b->Upload("f1", std::span(r1).subspan(10)).ok());

  EngineOptions long_segments = options;
  long_segments.segment_size = 1000;
  std::unique_ptr<MemoryStore> store_c = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> c = OpenOn(long_segments, store_c.get());
  ASSERT_NE(c, nullptr);
  ASSERT_TRUE(c->Upload("f1", r1).ok());
  ASSERT_TRUE(c->Consolidate("f1").ok());

  const std::vector<std::vector<uint64_t>> expected = membership(*a);
  EXPECT_EQ(expected.size(), 4u);
  EXPECT_EQ(membership(*b), expected);
  EXPECT_EQ(membership(*c), expected);
}

// An upload that would fill a segment but is refused is never planned: a
// code of another dimension must not reach k-means (it would overrun the
// plan's matrix before PrepareUpload refuses the upload).
TEST_F(MemoryEngineTest, ARefusedUploadThatWouldFillASegmentIsNotPlanned) {
  MustUpload(MakeTraces("r1", 1, 5, rng_));
  std::vector<core::MemoryTrace> bad = MakeTraces("r1", 6, 15, rng_);
  // The segment's last column: past it, the overrun leaves the matrix.
  bad.back().code.resize(kDimension + 9, 1.0f);
  absl::StatusOr<UploadResult> result = engine_->Upload("f1", bad);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  bad.back().code.resize(kDimension - 3);
  result = engine_->Upload("f1", bad);
  EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(Stats().pending_traces, 5u);
  EXPECT_EQ(Stats().clusters, 0u);
}

TEST_F(MemoryEngineTest, StoreFailureDuringReplayKeepsCounts) {
  FlakyStore flaky(store_.get());
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options_, &flaky, ExactFactory());
  ASSERT_TRUE(opened.ok());
  MemoryEngine& engine = **opened;
  ASSERT_TRUE(engine.Upload("f1", MakeTraces("r1", 1, 20, rng_)).ok());
  flaky.fail_after = flaky.applies;
  EXPECT_EQ(engine.SampleReplay("f1", "r1", 5).status().code(),
            absl::StatusCode::kInternal);
  flaky.fail_after = -1;
  for (const core::MemoryTrace& trace : AllTraces(engine, "f1", 200)) {
    EXPECT_EQ(trace.replay_count, 0u);
  }
  absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(FindRobot(*stats, "r1")->replayed, 0u);
}

// One copy of each code: once the index holds a static-memory trace's code,
// memory frees its own, and every way a trace leaves the engine (queries,
// listings, samples and the store write of their counts, a reload) still
// gives the code bit for bit.
TEST_F(MemoryEngineTest, CodesTheIndexHoldsAreFreedAndStillReturnedExactly) {
  auto control = std::make_shared<SwitchedCodeIndex::Switch>();
  auto open = [&]() -> std::unique_ptr<MemoryEngine> {
    absl::StatusOr<std::unique_ptr<MemoryEngine>> engine =
        MemoryEngine::Open(options_, store_.get(), [control](size_t dimension) {
          return std::make_unique<SwitchedCodeIndex>(dimension, control);
        });
    EXPECT_TRUE(engine.ok()) << engine.status();
    return engine.ok() ? *std::move(engine) : nullptr;
  };
  engine_ = open();
  std::map<core::TraceKey, std::vector<float>> uploaded;
  auto upload = [&](const std::string& robot, uint64_t first, size_t count) {
    std::vector<core::MemoryTrace> traces =
        MakeTraces(robot, first, count, rng_);
    for (const core::MemoryTrace& trace : traces) {
      uploaded[trace.key()] = trace.code;
    }
    MustUpload(traces);
  };
  auto expect_uploaded_codes = [&](const std::vector<core::MemoryTrace>& got) {
    for (const core::MemoryTrace& trace : got) {
      auto it = uploaded.find(trace.key());
      ASSERT_NE(it, uploaded.end());
      ASSERT_EQ(trace.code.size(), kDimension) << trace.seq;
      EXPECT_EQ(std::memcmp(trace.code.data(), it->second.data(),
                            kDimension * sizeof(float)),
                0)
          << trace.robot_id << " " << trace.seq;
    }
  };
  int samples = 0;
  auto expect_codes_every_way = [&] {
    expect_uploaded_codes(AllTraces(*engine_, "f1", 200));
    absl::StatusOr<TracePage> page =
        engine_->ListTraces("f1", std::nullopt, 1000);
    ASSERT_TRUE(page.ok()) << page.status();
    expect_uploaded_codes(page->traces);
    const std::string request = absl::StrCat("sample-", ++samples);
    for (int call = 0; call < 2; ++call) {  // the second is a retry
      absl::StatusOr<std::vector<core::MemoryTrace>> sample =
          engine_->SampleReplay("f1", "r1", 5, request);
      ASSERT_TRUE(sample.ok()) << sample.status();
      ASSERT_FALSE(sample->empty());
      expect_uploaded_codes(*sample);
    }
  };

  upload("r1", 1, 40);
  upload("r2", 1, 45);  // four segments and five pending traces
  const uint64_t clustered = Stats().traces;
  ASSERT_GT(clustered, 0u);
  expect_codes_every_way();
  EXPECT_EQ(control->copies, 0);  // memory kept every code

  control->holds = true;
  EXPECT_EQ(engine_->ReleaseIndexedCodes(), clustered);
  expect_codes_every_way();
  EXPECT_GT(control->copies, 0);

  // A consolidation frees the codes of its clusters itself.
  upload("r1", 41, 20);
  EXPECT_EQ(engine_->ReleaseIndexedCodes(), 0u);
  expect_codes_every_way();

  // A load frees them at once; the counts were stored with their codes.
  const int copies_before = control->copies;
  const FleetStats before = Stats();
  engine_.reset();
  engine_ = open();
  ExpectSameStats(Stats(), before);
  EXPECT_EQ(engine_->ReleaseIndexedCodes(), 0u);
  expect_codes_every_way();
  EXPECT_GT(control->copies, copies_before);
}

}  // namespace
}  // namespace fleetmem::engine
