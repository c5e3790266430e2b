// MemoryEngine: options, uploads, consolidation, export, replay, queries,
// events and quotas.
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
#include "services/engine/testing/forwarding_store.h"
#include "services/index/exact_index.h"
#include "services/index/hnsw_index.h"
#include "services/storage/in_memory_store.h"
#include "services/testing/memory_engine_test_util.h"

namespace fleetmem::engine {
namespace {

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

  // A deleted fleet's image: no traces, its position and ids; restored, it
  // leaves the fleet deleted there, and the id makes a new fleet.
  const uint64_t next_event = engine_->GetStats("f1")->last_event_id + 1;
  ASSERT_TRUE(engine_->DeleteFleet("f1", 50).ok());
  absl::StatusOr<FleetImage> gone = engine_->ExportFleet("f1", 51);
  ASSERT_TRUE(gone.ok()) << gone.status();
  EXPECT_EQ(gone->record.meta.code_dimension, 0u);
  EXPECT_EQ(gone->record.meta.log_position, 51u);
  EXPECT_EQ(gone->record.meta.next_event_id, next_event);
  EXPECT_TRUE(gone->record.clusters.empty() && gone->record.pending.empty());
  ASSERT_TRUE(other->RestoreFleet("f1", *gone).ok());
  EXPECT_TRUE(absl::IsNotFound(other->GetStats("f1").status()));
  EXPECT_EQ(*other->LogPosition("f1"), 51u);
  std::vector<core::MemoryTrace> remade = MakeTraces("r1", 1, 5, rng_);
  for (core::MemoryTrace& t : remade) t.code.resize(3);
  ASSERT_TRUE(other->Upload("f1", remade, 52).ok());
  EXPECT_EQ(other->GetStats("f1")->pending_traces, 5u);
  EXPECT_EQ(other->GetStats("f1")->code_dimension, 3u);
  // A deleted image that holds traces is no deleted fleet's.
  gone->record.pending = remade;
  EXPECT_TRUE(absl::IsInvalidArgument(other->RestoreFleet("f1", *gone)));
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

// No read returns more than max_read_bytes of traces: a page ends early, a
// sample or query that might be over it is refused before anything changes.
TEST_F(MemoryEngineTest, ReadsStayWithinMaxReadBytes) {
  // Each trace: 4 x 8 code bytes + its attachment.
  options_.max_read_bytes = 3 * (32 + 100);
  engine_ = OpenEngine();
  std::vector<core::MemoryTrace> traces = MakeTraces("r1", 1, 10, rng_);
  for (core::MemoryTrace& trace : traces) trace.attachment.assign(100, 'a');
  MustUpload(traces);

  std::vector<uint64_t> seqs;
  std::optional<core::TraceKey> after;
  for (bool more = true; more;) {
    absl::StatusOr<TracePage> page = engine_->ListTraces("f1", after, 1000);
    ASSERT_TRUE(page.ok()) << page.status();
    ASSERT_THAT(page->traces, SizeIs(::testing::Le(3u)));
    for (const core::MemoryTrace& trace : page->traces) {
      seqs.push_back(trace.seq);
    }
    after = page->traces.back().key();
    more = page->more;
  }
  EXPECT_THAT(seqs, SizeIs(10));  // every trace once, in order
  EXPECT_TRUE(std::is_sorted(seqs.begin(), seqs.end()));
  EXPECT_EQ(std::adjacent_find(seqs.begin(), seqs.end()), seqs.end());

  // A trace larger than the bound alone still comes, one per page.
  options_.max_read_bytes = 10;
  engine_ = OpenEngine();
  absl::StatusOr<TracePage> one = engine_->ListTraces("f1", std::nullopt, 5);
  ASSERT_TRUE(one.ok()) << one.status();
  EXPECT_THAT(one->traces, SizeIs(1));
  EXPECT_TRUE(one->more);

  // A query counts its matches' bytes: two fit, three do not.
  PlaceQuery query;
  query.code = traces[0].code;
  query.k = 3;
  options_.max_read_bytes = 2 * (32 + 100);
  engine_ = OpenEngine();
  absl::StatusOr<std::vector<PlaceMatch>> matches =
      engine_->QueryPlace("f1", query);
  ASSERT_TRUE(absl::IsInvalidArgument(matches.status())) << matches.status();
  EXPECT_THAT(matches.status().message(), HasSubstr("max_read_bytes"));
  query.k = 2;
  EXPECT_TRUE(engine_->QueryPlace("f1", query).ok());

  // A sample, drawn before its traces are known, counts the largest
  // attachment of the fleet's traces, and is refused before anything
  // changes.
  options_.max_read_bytes = 2 * (32 + 100);
  engine_ = OpenEngine();
  const FleetStats before = Stats();
  absl::StatusOr<std::vector<core::MemoryTrace>> sample =
      engine_->SampleReplay("f1", "r1", 3);
  ASSERT_TRUE(absl::IsInvalidArgument(sample.status())) << sample.status();
  EXPECT_THAT(sample.status().message(), HasSubstr("at most 2 traces"));
  EXPECT_THAT(sample.status().message(), HasSubstr("max_read_bytes"));
  EXPECT_EQ(Stats().robots.front().replayed, before.robots.front().replayed);
  EXPECT_TRUE(engine_->SampleReplay("f1", "r1", 2).ok());
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

}  // namespace
}  // namespace fleetmem::engine
