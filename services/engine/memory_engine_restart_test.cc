// MemoryEngine across restarts: reloads and index snapshots.
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
#include "services/testing/memory_engine_test_util.h"

namespace fleetmem::engine {
namespace {

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
    // The same calls give the same graph: no background thread, and one
    // inserting thread (with two, the graph depends on how they interleave,
    // and a trace's search for itself missed once in a run of `make
    // test-asan` beside another test, 2026-11-28).
    options.background = false;
    options.hnsw.insert_threads = 1;
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

// Forwards to the engine's store with its index snapshots and counts how
// fleets are read.
class LoadCountingStore : public ForwardingStore {
 public:
  explicit LoadCountingStore(MemoryStore* inner)
      : ForwardingStore(inner), inner_(inner) {}
  absl::StatusOr<FleetRecord> LoadFleetWithoutHeldCodes(
      std::string_view fleet_id,
      const std::function<bool(const core::TraceKey&)>& code_held_elsewhere)
      override {
    ++with_clusters;
    return inner_->LoadFleetWithoutHeldCodes(fleet_id, code_held_elsewhere);
  }
  absl::StatusOr<FleetRecord> LoadFleetWithoutClusters(
      std::string_view fleet_id) override {
    ++without_clusters;
    return inner_->LoadFleetWithoutClusters(fleet_id);
  }
  absl::Status SaveIndexSnapshot(
      std::string_view fleet_id,
      const std::function<absl::Status(core::ByteWriter&)>& write,
      const std::function<void()>& written) override {
    return inner_->SaveIndexSnapshot(fleet_id, write, written);
  }
  absl::Status ReadIndexSnapshot(std::string_view fleet_id,
                                 const IndexSnapshotRead& read) override {
    if (!fail_checks) return inner_->ReadIndexSnapshot(fleet_id, read);
    // The same bytes, whose checksum fails as a damaged file's would.
    return inner_->ReadIndexSnapshot(
        fleet_id, [&read](const IndexSnapshotBytes& snapshot) {
          IndexSnapshotBytes damaged = snapshot;
          damaged.check = [] {
            return absl::DataLossError("fails its checksum (test)");
          };
          const absl::Status status = read(damaged);
          return status.ok() ? damaged.check() : status;
        });
  }
  bool IndexSnapshotCurrent(std::string_view fleet_id) override {
    return report_current && inner_->IndexSnapshotCurrent(fleet_id);
  }

  bool report_current = true;  // false: every load reads the store
  bool fail_checks = false;    // every snapshot's checksum fails
  int with_clusters = 0;
  int without_clusters = 0;

 private:
  MemoryStore* inner_;
};

// Every held trace with every field, by key (for comparing two loads).
std::map<core::TraceKey, std::string> Described(const MemoryEngine& engine) {
  std::map<core::TraceKey, std::string> described;
  for (const core::MemoryTrace& t : AllTraces(engine, "f1", 5000)) {
    std::string& out = described[t.key()];
    out = absl::StrCat(t.domain, " ", t.encoder_version, " ", t.place.x, " ",
                       t.place.y, " ", t.reward, " ", t.reward_external, " ",
                       t.reward_internal, " ", t.timestamp_ns, " ",
                       t.replay_count, " ", t.cluster_id, " ", t.attachment,
                       " ", t.code.size());
    for (float value : t.code) absl::StrAppend(&out, ",", value);
  }
  return described;
}

// After a clean stop the fleet's snapshot describes the store exactly: the
// next start takes the clusters from its memory image and reads none from
// the store, and holds what the store would have given (replay counts and
// rewards written after the snapshot's index included). A write after it
// (a replay draw) makes the store's read come back; a stop's save writes
// the snapshot again although its index did not change.
TEST_F(IndexSnapshotTest, CleanStopLoadsTheClustersFromTheMemoryImage) {
  LoadCountingStore counting(store_.get());
  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  UploadSegments("r1", 1, 600);
  UploadSegments("r2", 1, 400);
  MustUpload(MakeTraces("r3", 1, 70, rng_));  // stays pending
  ASSERT_TRUE(engine_->SampleReplay("f1", "r1", 50).ok());
  const std::vector<core::MemoryTrace> some = AllTraces(*engine_, "f1", 20);
  std::vector<core::RewardUpdate> rewards;
  for (const core::MemoryTrace& trace : some) {
    rewards.push_back({trace.key(), 2.5f, 0.5f});
  }
  ASSERT_TRUE(engine_->UpdateRewards("f1", rewards).ok());
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  const FleetStats stats = Stats();
  const auto described = Described(*engine_);
  const std::vector<core::MemoryTrace> queries = MakeTraces("q", 1, 30, rng_);
  const auto nearest = Nearest(queries);

  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(counting.with_clusters, 0);
  EXPECT_EQ(counting.without_clusters, 1);
  EXPECT_EQ(loads_.load(), 1);
  ExpectSameStats(Stats(), stats);
  EXPECT_EQ(Described(*engine_), described);
  EXPECT_EQ(Nearest(queries), nearest);
  ExpectEveryTraceFindsItself();

  // A replay draw writes the store, not the index: no longer current, so a
  // crash's restart reads the store, and gets the new counts.
  ASSERT_TRUE(engine_->SampleReplay("f1", "r2", 50).ok());
  const auto drawn = Described(*engine_);
  ASSERT_NE(drawn, described);
  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(counting.with_clusters, 1);
  EXPECT_EQ(Described(*engine_), drawn);
  // A periodic save skips the unchanged index; a stop's writes it again.
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_FALSE(counting.IndexSnapshotCurrent("f1"));
  ASSERT_TRUE(engine_
                  ->SaveIndexSnapshots(
                      {.only_changed = true, .refresh_memory_image = true})
                  .ok());
  EXPECT_TRUE(counting.IndexSnapshotCurrent("f1"));
  const int saves = saves_.load();
  ASSERT_TRUE(engine_
                  ->SaveIndexSnapshots(
                      {.only_changed = true, .refresh_memory_image = true})
                  .ok());
  EXPECT_EQ(saves_.load(), saves);  // current for both: not written again
  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(counting.with_clusters, 1);
  EXPECT_EQ(counting.without_clusters, 2);
  EXPECT_EQ(Described(*engine_), drawn);
}

// Forgetting's centroids come with the memory image, and memory reads them
// where the snapshot's thread left them (borrowed from the store's bytes,
// valid until that read returns: the in-memory store scribbles over its
// copy then): a load from the image and one from the store's records both
// take them, neither rebuilds them.
TEST_F(IndexSnapshotTest, ALoadTakesForgettingsCentroidsFromTheSnapshot) {
  LoadCountingStore counting(store_.get());
  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  for (const char* robot : {"r1", "r2", "r3"}) UploadSegments(robot, 1, 400);
  ASSERT_GT(Stats().clusters_forgotten, 0u);  // the centroids in use
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  for (const bool current : {true, false}) {
    SCOPED_TRACE(current ? "from the memory image" : "from the records");
    counting.report_current = current;
    testing::internal::CaptureStderr();
    engine_ = Open(nullptr, &counting);
    const std::string log = testing::internal::GetCapturedStderr();
    ASSERT_NE(engine_, nullptr);
    EXPECT_EQ(log.find("memory image in") != std::string::npos, current) << log;
    EXPECT_NE(log.find("index snapshot reconciled"), std::string::npos) << log;
    EXPECT_EQ(log.find("centroid graph rebuilt"), std::string::npos) << log;
    ExpectEveryTraceFindsItself();
  }
}

// The memory image is parsed while the store checks the snapshot's
// checksum (IndexSnapshotBytes): a snapshot that fails it is not used,
// however far its parse got. The clusters come from the store's records,
// the index is rebuilt from the store's codes, and the fleet holds what it
// held.
TEST_F(IndexSnapshotTest, AMemoryImageIsUsedOnlyOnceItsChecksumPassed) {
  LoadCountingStore counting(store_.get());
  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  UploadSegments("r1", 1, 600);
  MustUpload(MakeTraces("r2", 1, 70, rng_));  // stays pending
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  const FleetStats stats = Stats();
  const auto described = Described(*engine_);
  const std::vector<core::MemoryTrace> queries = MakeTraces("q", 1, 30, rng_);
  const auto nearest = Nearest(queries);
  const int loads = loads_.load();

  counting.fail_checks = true;
  engine_ = Open(nullptr, &counting);
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(counting.without_clusters, 1);  // the image was read
  EXPECT_EQ(counting.with_clusters, 1);     // and not used
  EXPECT_EQ(loads_.load(), loads);          // nor the index
  ExpectSameStats(Stats(), stats);
  EXPECT_EQ(Described(*engine_), described);
  EXPECT_EQ(Nearest(queries), nearest);
  ExpectEveryTraceFindsItself();
}

// Forgetting goes on after a load from the memory image exactly as after
// the store's read of the same state (the image's centroids are the
// store's, feature and place: forgetting's tracker loads, not rebuilt):
// two stores filled alike, one loaded each way, the same uploads after.
TEST_F(IndexSnapshotTest, MemoryImageForgetsAsTheStoresRecordsWould) {
  std::unique_ptr<MemoryStore> second = storage::NewInMemoryStore();
  LoadCountingStore imaged(store_.get());
  LoadCountingStore recorded(second.get());
  recorded.report_current = false;
  struct Run {
    FleetStats stats;
    std::vector<std::string> events;
    std::vector<std::vector<core::TraceKey>> nearest;
  };
  const std::vector<core::MemoryTrace> queries = MakeTraces("q", 1, 30, rng_);
  auto run = [&](LoadCountingStore& store) {
    rng_.seed(11);
    engine_ = Open(nullptr, &store);
    UploadSegments("r1", 1, 500);
    UploadSegments("r2", 1, 400);
    EXPECT_GT(Stats().clusters_forgotten, 0u);
    EXPECT_TRUE(engine_->SaveIndexSnapshots().ok());
    engine_ = Open(nullptr, &store);  // the load under test
    UploadSegments("r1", 501, 900);
    UploadSegments("r3", 1, 300);
    Run result{Stats(), {}, Nearest(queries)};
    absl::StatusOr<std::vector<core::MemoryEvent>> events =
        engine_->ReadEvents("f1", 0);
    EXPECT_TRUE(events.ok()) << events.status();
    if (!events.ok()) return result;
    for (const core::MemoryEvent& e : *events) {
      result.events.push_back(absl::StrCat(e.id, " ", static_cast<int>(e.type),
                                           " ", e.cluster_id, " ",
                                           e.trace_count, " ", e.merged_into));
    }
    return result;
  };
  const Run from_image = run(imaged);
  EXPECT_EQ(imaged.with_clusters, 0);
  EXPECT_EQ(imaged.without_clusters, 1);
  const Run from_records = run(recorded);
  EXPECT_EQ(recorded.with_clusters, 1);
  ExpectSameStats(from_image.stats, from_records.stats);
  EXPECT_GT(from_image.stats.clusters_forgotten, 0u);
  EXPECT_EQ(from_image.events, from_records.events);
  EXPECT_EQ(from_image.nearest, from_records.nearest);
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

// A CountingIndex that says it met damage (PlaceIndex::Damaged: a row read
// from its snapshot's file failed its check) once `*damaged` reaches its
// number (indexes are numbered as they are made, from 1).
class DamageableIndex : public CountingIndex {
 public:
  DamageableIndex(size_t dimension, std::atomic<int>* loads, int number,
                  const std::atomic<int>* damaged)
      : CountingIndex(dimension, loads), number_(number), damaged_(damaged) {}
  bool Damaged() const override { return damaged_->load() >= number_; }

 private:
  const int number_;
  const std::atomic<int>* damaged_;
};

// A damaged index is rebuilt from the store's codes, not from its snapshot
// (which would bring the damage back): at the fleet's next snapshot,
// before it is written, and at its next write. Everything is as before.
TEST_F(IndexSnapshotTest, ADamagedIndexIsRebuiltFromTheStore) {
  std::atomic<int> made{0};
  std::atomic<int> damaged{0};
  auto factory = [&](size_t dimension) {
    return std::make_unique<DamageableIndex>(dimension, &loads_, ++made,
                                             &damaged);
  };
  engine_ = Open(factory);
  ASSERT_NE(engine_, nullptr);
  UploadSegments("r1", 1, 600);
  MustUpload(MakeTraces("r2", 1, 50, rng_));  // pending
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  engine_ = Open(factory);
  ASSERT_NE(engine_, nullptr);
  ASSERT_EQ(loads_.load(), 1);
  const FleetStats stats = Stats();
  const std::vector<core::MemoryTrace> queries = MakeTraces("q", 1, 20, rng_);
  const auto before = Nearest(queries);

  // At the next snapshot: a new index, not loaded from the file, then
  // saved.
  saves_ = 0;
  damaged = made.load();
  ASSERT_TRUE(engine_->SaveIndexSnapshots({.only_changed = true}).ok());
  EXPECT_EQ(loads_.load(), 1);
  EXPECT_GT(made.load(), damaged.load());
  EXPECT_EQ(saves_.load(), 1);
  ExpectSameStats(Stats(), stats);
  ExpectEveryTraceFindsItself();
  ExpectOnlyHeldKeys(Nearest(queries));
  EXPECT_EQ(Nearest(queries).size(), before.size());

  // At the next write.
  damaged = made.load();
  MustUpload(MakeTraces("r2", 51, 10, rng_));
  EXPECT_EQ(loads_.load(), 1);
  EXPECT_GT(made.load(), damaged.load());
  EXPECT_EQ(Stats().pending_traces, stats.pending_traces + 10);
  ExpectEveryTraceFindsItself();
  engine_.reset();  // before the counters its indexes point to
}

// A snapshot whose codes differ from the store's under the same keys (the
// fleet of another server's history) is refused and the index rebuilt.
TEST_F(IndexSnapshotTest, SnapshotOfAnotherHistoryIsRebuilt) {
  UploadSegments("r1", 1, 400);
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  std::vector<char> bytes;
  ASSERT_TRUE(
      store_
          ->ReadIndexSnapshot("f1",
                              [&bytes](const IndexSnapshotBytes& snapshot) {
                                bytes.assign(snapshot.bytes.begin(),
                                             snapshot.bytes.end());
                                return absl::OkStatus();
                              })
          .ok());
  // The same keys with other codes, in another store, with the snapshot
  // (put there before those writes: a snapshot saved after a fleet's last
  // write is taken as its exact state, memory image included).
  std::unique_ptr<MemoryStore> other = storage::NewInMemoryStore();
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
  UploadSegments("r1", 1, 400);
  engine_.reset();
  ASSERT_FALSE(other->IndexSnapshotCurrent("f1"));
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

}  // namespace
}  // namespace fleetmem::engine
