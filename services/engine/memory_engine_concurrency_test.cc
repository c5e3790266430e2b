// MemoryEngine under concurrency and store failures: listeners, hooks,
// racing calls, failed writes, segment plans, codes held once.
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
  hooks.on_consolidate = [&](std::string_view, size_t,
                             const ConsolidateResult& result, double seconds) {
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

// A consolidation is written to the store under the shared lock: queries,
// stats and event reads go on while its write waits, and already see the
// consolidation in memory; its events are read once they are stored.
TEST_F(MemoryEngineTest, ReadersDoNotWaitForAConsolidationsStoreWrite) {
  GatedStore gated(store_.get());
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options_, &gated, ExactFactory());
  ASSERT_TRUE(opened.ok()) << opened.status();
  MemoryEngine& engine = **opened;
  const std::vector<core::MemoryTrace> traces =
      MakeTraces("r1", 1, options_.segment_size, rng_);
  const std::vector<core::MemoryTrace> first(traces.begin(),
                                             traces.begin() + 5);
  const std::vector<core::MemoryTrace> rest(traces.begin() + 5, traces.end());
  ASSERT_TRUE(engine.Upload("f1", first).ok());

  gated.Hold();
  std::thread uploader([&] {
    absl::StatusOr<UploadResult> result = engine.Upload("f1", rest);
    ASSERT_TRUE(result.ok()) << result.status();
    EXPECT_EQ(result->consolidations, 1u);
  });
  gated.AwaitWaiting(1);
  for (int i = 0; i < 5; ++i) {
    absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
    ASSERT_TRUE(stats.ok()) << stats.status();
    EXPECT_EQ(stats->pending_traces, 0u);  // consolidated in memory
    EXPECT_GT(stats->clusters, 0u);
    EXPECT_EQ(stats->last_event_id, 0u);  // none stored yet
    PlaceQuery query;
    query.code = rest[0].code;
    query.k = 1;
    absl::StatusOr<std::vector<PlaceMatch>> found =
        engine.QueryPlace("f1", query);
    ASSERT_TRUE(found.ok()) << found.status();
    ASSERT_EQ(found->size(), 1u);
    EXPECT_EQ(found->front().trace.code.size(), rest[0].code.size());
    absl::StatusOr<std::vector<core::MemoryEvent>> events =
        engine.ReadEvents("f1", 0);
    ASSERT_TRUE(events.ok()) << events.status();
    EXPECT_TRUE(events->empty());
  }
  gated.Release();
  uploader.join();
  absl::StatusOr<FleetStats> after = engine.GetStats("f1");
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_GT(after->last_event_id, 0u);
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine.ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok()) << events.status();
  EXPECT_EQ(events->size(), after->last_event_id);
  // And the store agrees after a reopen.
  absl::StatusOr<std::unique_ptr<MemoryEngine>> reopened =
      MemoryEngine::Open(options_, store_.get(), ExactFactory());
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  absl::StatusOr<FleetStats> again = (*reopened)->GetStats("f1");
  ASSERT_TRUE(again.ok()) << again.status();
  ExpectSameStats(*after, *again);
}

// Retention erases events in a consolidation's store write, before the
// fleet's meta says so (StoreStaged publishes it after the write): a reader
// whose cursor fell behind meanwhile gets OUT_OF_RANGE, never a silent gap.
TEST_F(MemoryEngineTest, EventsErasedBesideAReaderAreReportedAsErased) {
  options_.max_events_per_fleet = 5;
  GatedStore gated(store_.get());
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options_, &gated, ExactFactory());
  ASSERT_TRUE(opened.ok()) << opened.status();
  MemoryEngine& engine = **opened;
  const size_t segment = options_.segment_size;
  ASSERT_TRUE(engine.Upload("f1", MakeTraces("r1", 1, segment, rng_)).ok());
  absl::StatusOr<FleetStats> before = engine.GetStats("f1");
  ASSERT_TRUE(before.ok()) << before.status();
  ASSERT_EQ(before->first_event_id, 1u);
  ASSERT_GT(before->last_event_id, 1u);

  gated.Hold(/*after_write=*/true);
  std::thread uploader([&] {
    EXPECT_TRUE(
        engine.Upload("f1", MakeTraces("r1", 1 + segment, segment, rng_)).ok());
  });
  gated.AwaitWaiting(1);  // written, events 1.. erased; meta not yet
  absl::StatusOr<FleetStats> during = engine.GetStats("f1");
  ASSERT_TRUE(during.ok()) << during.status();
  EXPECT_EQ(during->first_event_id, 1u);
  const absl::Status gone = engine.ReadEvents("f1", 1).status();
  EXPECT_EQ(gone.code(), absl::StatusCode::kOutOfRange) << gone;
  EXPECT_THAT(gone.message(), HasSubstr("retention"));
  gated.Release();
  uploader.join();
  absl::StatusOr<FleetStats> after = engine.GetStats("f1");
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_GT(after->first_event_id, 2u);
  EXPECT_EQ(engine.ReadEvents("f1", 1).status().code(),
            absl::StatusCode::kOutOfRange);
}

// An engine whose fleets' traces stay pending (and indexed) in a tiered
// index with a graph from 10 codes on (back-pressure past max_unindexed).
std::unique_ptr<MemoryEngine> OpenTiered(MemoryStore* store,
                                         size_t max_unindexed) {
  EngineOptions options = SmallOptions();
  options.segment_size = 1000;
  absl::StatusOr<std::unique_ptr<MemoryEngine>> opened =
      MemoryEngine::Open(options, store, [max_unindexed](size_t dimension) {
        index::TieredIndexOptions tiered;
        tiered.hnsw_from = 10;
        tiered.max_unindexed = max_unindexed;
        return index::NewTieredIndex(dimension, tiered);
      });
  EXPECT_TRUE(opened.ok()) << opened.status();
  return opened.ok() ? *std::move(opened) : nullptr;
}

// GetStats reports the place index's backlog: with the tiered index, whose
// graph fills in the background, the codes not yet in the graph, until the
// background thread has moved them all; with the exact index, none.
TEST_F(MemoryEngineTest, StatsReportTheIndexBacklog) {
  std::unique_ptr<MemoryStore> store = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> opened =
      OpenTiered(store.get(), index::TieredIndexOptions().max_unindexed);
  ASSERT_NE(opened, nullptr);
  MemoryEngine& engine = *opened;
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

// A bulk load defers the fleet's graph: the codes uploaded meanwhile wait
// in the exact segment (found by queries, counted as unindexed), none is
// linked in the background, and IndexDeferred builds the graph from all of
// them at once. A deferral also ends by itself when its time passes.
TEST_F(MemoryEngineTest, ADeferredIndexIsBuiltOnceAtTheEnd) {
  std::unique_ptr<MemoryStore> store = storage::NewInMemoryStore();
  // Back-pressure past 20 codes, but for the deferral.
  std::unique_ptr<MemoryEngine> opened = OpenTiered(store.get(), 20);
  ASSERT_NE(opened, nullptr);
  MemoryEngine& engine = *opened;
  EXPECT_EQ(engine.DeferIndexing("f1", absl::InfiniteFuture()).code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(engine.IndexDeferred("f1").code(), absl::StatusCode::kNotFound);
  const std::vector<core::MemoryTrace> first = MakeTraces("r1", 1, 5, rng_);
  ASSERT_TRUE(engine.Upload("f1", first).ok());
  ASSERT_TRUE(engine.DeferIndexing("f1", absl::InfiniteFuture()).ok());
  EXPECT_TRUE(engine.IndexingDeferred("f1"));
  std::vector<core::MemoryTrace> traces = first;
  for (uint64_t seq = 6; seq <= 205; seq += 50) {
    std::vector<core::MemoryTrace> more = MakeTraces("r1", seq, 50, rng_);
    ASSERT_TRUE(engine.Upload("f1", more).ok());
    traces.insert(traces.end(), more.begin(), more.end());
  }
  absl::SleepFor(absl::Milliseconds(50));  // a background step, if any
  absl::StatusOr<FleetStats> stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->pending_traces, 205u);
  EXPECT_EQ(stats->unindexed_codes, 205u);  // nothing linked meanwhile
  // Found all the same (the exact scan).
  absl::StatusOr<std::vector<PlaceMatch>> found =
      engine.QueryPlace("f1", {.code = traces[150].code, .k = 1});
  ASSERT_TRUE(found.ok()) << found.status();
  ASSERT_EQ(found->size(), 1u);
  EXPECT_EQ(found->front().trace.seq, traces[150].seq);

  ASSERT_TRUE(engine.IndexDeferred("f1").ok());
  EXPECT_FALSE(engine.IndexingDeferred("f1"));
  stats = engine.GetStats("f1");
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->unindexed_codes, 0u);
  for (size_t i : {0, 77, 204}) {
    found = engine.QueryPlace("f1", {.code = traces[i].code, .k = 1});
    ASSERT_TRUE(found.ok()) << found.status();
    ASSERT_EQ(found->size(), 1u);
    EXPECT_EQ(found->front().trace.seq, traces[i].seq) << i;
  }

  // A deferral that lapses: the background thread links what waits.
  const auto unindexed = [&] {
    absl::StatusOr<FleetStats> now = engine.GetStats("f1");
    return now.ok() ? now->unindexed_codes : uint64_t{999};
  };
  // (Checked only while the deferral holds: a slow build, ASan's, may
  // reach the deadline before the upload returns.)
  const absl::Time lapses = absl::Now() + absl::Seconds(1);
  ASSERT_TRUE(engine.DeferIndexing("f1", lapses).ok());
  ASSERT_TRUE(engine.Upload("f1", MakeTraces("r1", 206, 50, rng_)).ok());
  const uint64_t waiting = unindexed();
  if (absl::Now() < lapses) EXPECT_EQ(waiting, 50u);
  const absl::Time deadline = absl::Now() + absl::Seconds(60);
  while (unindexed() > 0 && absl::Now() < deadline) {
    absl::SleepFor(absl::Milliseconds(10));
  }
  EXPECT_EQ(unindexed(), 0u);
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
