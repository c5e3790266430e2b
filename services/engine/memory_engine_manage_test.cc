// MemoryEngine's DeleteTraces, UpdateRewards and GetTraces: what is
// deleted is never returned again by any read, in memory or after a
// reopen; rewards change the replay draw; lookups by key.
#include <algorithm>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/engine/memory_engine.h"
#include "services/engine/testing/forwarding_store.h"
#include "services/index/exact_index.h"
#include "services/testing/memory_engine_test_util.h"

namespace fleetmem::engine {
namespace {

core::TraceFilter OfRobot(std::string robot_id) {
  core::TraceFilter filter;
  filter.robot_id = std::move(robot_id);
  return filter;
}

class ManageTest : public MemoryEngineTest {
 protected:
  // Two robots with consolidated segments and pending traces in one fleet.
  void Fill() {
    for (int segment = 0; segment < 4; ++segment) {
      const std::string robot = segment % 2 == 0 ? "r1" : "r2";
      MustUpload(MakeTraces(robot, 1 + 20 * (segment / 2), 20, rng_));
    }
    MustUpload(MakeTraces("r1", 41, 7, rng_));  // pending
    MustUpload(MakeTraces("r2", 41, 5, rng_));  // pending
  }

  // Every trace any read returns: a query for all, the listing, a sample
  // of all, the clusters' places.
  std::set<std::string> RobotsAnyReadReturns() {
    std::set<std::string> robots;
    for (const core::MemoryTrace& trace : AllTraces(*engine_, "f1", 200)) {
      robots.insert(trace.robot_id);
    }
    absl::StatusOr<TracePage> page =
        engine_->ListTraces("f1", std::nullopt, 1000);
    EXPECT_TRUE(page.ok()) << page.status();
    if (page.ok()) {
      EXPECT_EQ(page->total, Stats().traces + Stats().pending_traces);
      for (const core::MemoryTrace& trace : page->traces) {
        robots.insert(trace.robot_id);
      }
    }
    absl::StatusOr<std::vector<core::MemoryTrace>> sample =
        engine_->SampleReplay("f1", "reader", 100);
    EXPECT_TRUE(sample.ok()) << sample.status();
    if (sample.ok()) {
      for (const core::MemoryTrace& trace : *sample) {
        robots.insert(trace.robot_id);
      }
    }
    absl::StatusOr<ClusterListing> clusters = engine_->ListClusters("f1", true);
    EXPECT_TRUE(clusters.ok());
    if (clusters.ok()) {
      for (const ClusterSummary& cluster : clusters->clusters) {
        for (const auto& [robot, count] : cluster.robots) robots.insert(robot);
      }
      for (const TracePlace& place : clusters->pending) {
        robots.insert(place.robot_id);
      }
    }
    return robots;
  }
};

TEST_F(ManageTest, ADeletedRobotsTracesAreNeverReturnedAgain) {
  Fill();
  const FleetStats before = Stats();
  ASSERT_EQ(RobotsAnyReadReturns(), (std::set<std::string>{"r1", "r2"}));
  const uint64_t r2_held =
      FindRobot(before, "r2")->traces + FindRobot(before, "r2")->pending_traces;

  absl::StatusOr<DeleteResult> deleted =
      engine_->DeleteTraces("f1", OfRobot("r2"));
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_EQ(deleted->deleted, r2_held);
  EXPECT_EQ(deleted->pending_deleted, 5u);
  EXPECT_GE(deleted->clusters_changed + deleted->clusters_removed, 1u);

  const FleetStats after = Stats();
  EXPECT_EQ(after.traces + after.pending_traces,
            before.traces + before.pending_traces - r2_held);
  EXPECT_EQ(deleted->traces, after.traces + after.pending_traces);
  EXPECT_EQ(after.clusters, before.clusters - deleted->clusters_removed);
  EXPECT_EQ(FindRobot(after, "r2")->traces, 0u);
  EXPECT_EQ(FindRobot(after, "r2")->pending_traces, 0u);
  EXPECT_EQ(RobotsAnyReadReturns(), (std::set<std::string>{"r1"}));

  // The watch hears of it: one event per cluster touched, and the pending.
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", before.last_event_id);
  ASSERT_TRUE(events.ok());
  ASSERT_EQ(events->size(),
            1 + deleted->clusters_changed + deleted->clusters_removed);
  uint64_t dropped = 0;
  for (const core::MemoryEvent& event : *events) {
    EXPECT_EQ(event.type, core::EventType::kTracesDeleted);
    dropped += event.traces_dropped;
  }
  EXPECT_EQ(dropped, r2_held);

  // Stored as such: a reopened engine agrees, and a retry of r2's uploads
  // (its store-and-forward queue) is a duplicate, stored nowhere.
  const FleetStats stored = Stats();  // the reads above sampled
  engine_.reset();
  engine_ = OpenEngine();
  ExpectSameStats(Stats(), stored);
  EXPECT_EQ(RobotsAnyReadReturns(), (std::set<std::string>{"r1"}));
  EXPECT_EQ(MustUpload(MakeTraces("r2", 1, 20, rng_)).duplicates, 20u);
  EXPECT_EQ(RobotsAnyReadReturns(), (std::set<std::string>{"r1"}));
  // Forgetting and consolidation go on over what is left.
  MustUpload(MakeTraces("r3", 1, 20, rng_));
  EXPECT_LE(Stats().clusters,
            static_cast<uint64_t>(options_.memory.max_clusters));
}

TEST_F(ManageTest, ChangedClustersKeepTheirOtherTracesAndCentroids) {
  Fill();
  // Every summer trace (even seqs) of both robots, and a seq range of r1.
  core::TraceFilter summer;
  summer.domain = "summer";
  absl::StatusOr<DeleteResult> deleted = engine_->DeleteTraces("f1", summer);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_GT(deleted->deleted, 0u);
  core::TraceFilter range = OfRobot("r1");
  range.seq_first = 1;
  range.seq_last = 9;
  ASSERT_TRUE(engine_->DeleteTraces("f1", range).ok());
  absl::StatusOr<TracePage> page = engine_->ListTraces("f1", std::nullopt, 500);
  ASSERT_TRUE(page.ok());
  ASSERT_FALSE(page->traces.empty());
  for (const core::MemoryTrace& trace : page->traces) {
    EXPECT_EQ(trace.domain, "winter");
    EXPECT_FALSE(trace.robot_id == "r1" && trace.seq <= 9) << trace.seq;
  }
  // What is left still finds itself.
  ExpectEachTraceFindsItself(*engine_, page->traces);
  // A time range: [1000 * 41, 1000 * 44) holds r1's and r2's seqs 41..43.
  core::TraceFilter times;
  times.time_from_ns = 41'000;
  times.time_to_ns = 44'000;
  deleted = engine_->DeleteTraces("f1", times);
  ASSERT_TRUE(deleted.ok());
  EXPECT_EQ(deleted->deleted, 4u);  // the winter ones: 41, 43 of each
}

TEST_F(ManageTest, ALogEntryAppliedAgainChangesNothing) {
  Fill();
  core::TraceFilter late;
  late.time_from_ns = 45'000;
  absl::StatusOr<DeleteResult> first = engine_->DeleteTraces("f1", late, 900);
  ASSERT_TRUE(first.ok());
  EXPECT_GT(first->deleted, 0u);
  // Later traces that match the same selection, then the same entry again
  // (a restart applies the log from an older position): they stay.
  MustUpload(MakeTraces("r3", 50, 3, rng_));
  absl::StatusOr<DeleteResult> again = engine_->DeleteTraces("f1", late, 900);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->deleted, 0u);
  EXPECT_EQ(FindRobot(Stats(), "r3")->pending_traces, 3u);
  // A later entry applies.
  EXPECT_EQ(engine_->DeleteTraces("f1", late, 901)->deleted, 3u);
}

// DeleteFleet: nothing of the fleet is read again, in memory or after a
// reopen; its id makes a new fleet (the old robots' seqs forgotten), whose
// event ids go on after the old ones; its log entry applied again (a
// restart from an older position) changes nothing.
TEST_F(ManageTest, ADeletedFleetIsGoneAndItsIdMakesANewOne) {
  Fill();
  const FleetStats before = Stats();
  const uint64_t held = before.traces + before.pending_traces;
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(events.ok() && !events->empty());
  absl::StatusOr<uint64_t> deleted = engine_->DeleteFleet("f1", 500);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_EQ(*deleted, held);
  EXPECT_TRUE(absl::IsNotFound(engine_->GetStats("f1").status()));
  EXPECT_TRUE(
      absl::IsNotFound(engine_->ListTraces("f1", std::nullopt, 10).status()));
  EXPECT_TRUE(engine_->ListFleets().empty());
  EXPECT_EQ(engine_->ReadEvents("f1", 0)->size(), 0u);
  EXPECT_TRUE(absl::IsNotFound(engine_->DeleteFleet("f1").status()));
  EXPECT_EQ(*engine_->DeleteFleet("f1", 500), 0u);  // applied before
  absl::StatusOr<FleetRecord> stored = store_->LoadFleet("f1");
  ASSERT_TRUE(stored.ok());
  EXPECT_TRUE(stored->clusters.empty() && stored->pending.empty() &&
              stored->robots.empty());
  EXPECT_EQ(stored->meta.log_position, 500u);

  // Anew: r1's seqs again, another dimension, the server's settings.
  auto small = [this](uint64_t first, size_t count) {
    std::vector<core::MemoryTrace> traces =
        MakeTraces("r1", first, count, rng_);
    for (core::MemoryTrace& trace : traces) trace.code.resize(8);
    return traces;
  };
  MustUpload(small(1, 3));
  const FleetStats after = Stats();
  EXPECT_EQ(after.pending_traces + after.traces, 3u);
  EXPECT_EQ(after.code_dimension, 8u);
  MustUpload(small(4, 20));  // a segment: an event
  absl::StatusOr<std::vector<core::MemoryEvent>> later =
      engine_->ReadEvents("f1", 0);
  ASSERT_TRUE(later.ok() && !later->empty());
  EXPECT_GT(later->front().id, events->back().id);

  // Reopened, it is the new fleet.
  const FleetStats remade = Stats();
  engine_.reset();
  engine_ = OpenOn(options_, store_.get());
  ASSERT_NE(engine_, nullptr);
  EXPECT_EQ(Stats().code_dimension, 8u);
  ExpectSameStats(Stats(), remade);
}

TEST_F(ManageTest, BadSelectionsAreRefusedAndChangeNothing) {
  Fill();
  const FleetStats before = Stats();
  EXPECT_TRUE(absl::IsInvalidArgument(
      engine_->DeleteTraces("f1", core::TraceFilter{}).status()));
  core::TraceFilter seqs;
  seqs.seq_first = 1;
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->DeleteTraces("f1", seqs).status()));
  EXPECT_TRUE(absl::IsNotFound(
      engine_->DeleteTraces("nowhere", OfRobot("r1")).status()));
  EXPECT_TRUE(absl::IsInvalidArgument(
      engine_->DeleteTraces("bad fleet", OfRobot("r1")).status()));
  ExpectSameStats(Stats(), before);
  // Nothing matched: nothing deleted, no event.
  absl::StatusOr<DeleteResult> none =
      engine_->DeleteTraces("f1", OfRobot("nobody"));
  ASSERT_TRUE(none.ok());
  EXPECT_EQ(none->deleted, 0u);
  ExpectSameStats(Stats(), before);
}

TEST_F(ManageTest, AFailedStoreWriteDeletesNothing) {
  Fill();
  engine_.reset();
  FlakyStore flaky(store_.get());
  std::unique_ptr<MemoryEngine> engine = OpenOn(options_, &flaky);
  const FleetStats before = *engine->GetStats("f1");
  flaky.fail_after = flaky.applies;
  EXPECT_FALSE(engine->DeleteTraces("f1", OfRobot("r2")).ok());
  flaky.fail_after = -1;
  ExpectSameStats(*engine->GetStats("f1"), before);
  EXPECT_EQ(engine->DeleteTraces("f1", OfRobot("r2"))->deleted,
            FindRobot(before, "r2")->traces +
                FindRobot(before, "r2")->pending_traces);
}

TEST_F(ManageTest, NewRewardsChangeTheNextDrawAndAreStored) {
  Fill();
  absl::StatusOr<TracePage> page = engine_->ListTraces("f1", std::nullopt, 500);
  ASSERT_TRUE(page.ok());
  const core::MemoryTrace* held = nullptr;
  const core::MemoryTrace* pending = nullptr;
  for (const core::MemoryTrace& trace : page->traces) {
    if (trace.cluster_id != 0 && held == nullptr) held = &trace;
    if (trace.cluster_id == 0 && pending == nullptr) pending = &trace;
  }
  ASSERT_NE(held, nullptr);
  ASSERT_NE(pending, nullptr);
  // Every held trace nearly weightless but one.
  std::vector<core::RewardUpdate> updates;
  for (const core::MemoryTrace& trace : page->traces) {
    const bool favoured = trace.key() == held->key();
    updates.push_back(
        {trace.key(), favoured ? 1000.0f : 0.0f, favoured ? 5.0f : 0.0f});
  }
  updates.push_back({core::TraceKey{"r9", 1}, 1.0f, 1.0f});
  absl::StatusOr<RewardsResult> result = engine_->UpdateRewards("f1", updates);
  ASSERT_TRUE(result.ok()) << result.status();
  EXPECT_EQ(result->updated, page->traces.size());
  EXPECT_THAT(result->not_held, ElementsAre(core::TraceKey{"r9", 1}));

  const std::vector<core::TraceKey> keys = {held->key(), pending->key()};
  absl::StatusOr<TraceLookup> lookup = engine_->GetTraces("f1", keys);
  ASSERT_TRUE(lookup.ok());
  ASSERT_EQ(lookup->traces.size(), 2u);
  EXPECT_FLOAT_EQ(lookup->traces[0].reward, 1005.0f);
  EXPECT_FLOAT_EQ(lookup->traces[0].reward_external, 1000.0f);
  EXPECT_FLOAT_EQ(lookup->traces[1].reward, 0.0f);
  EXPECT_EQ(lookup->traces[0].code, held->code);

  absl::StatusOr<std::vector<core::MemoryTrace>> drawn =
      engine_->SampleReplay("f1", "r1", 1);
  ASSERT_TRUE(drawn.ok());
  EXPECT_EQ(drawn->front().key(), held->key());

  engine_.reset();
  engine_ = OpenEngine();
  lookup = engine_->GetTraces("f1", keys);
  ASSERT_TRUE(lookup.ok());
  EXPECT_FLOAT_EQ(lookup->traces[0].reward, 1005.0f);
  EXPECT_FLOAT_EQ(lookup->traces[1].reward, 0.0f);

  // Bad rewards: refused whole.
  // A trace named twice takes its last rewards, counted once.
  const std::vector<core::RewardUpdate> twice = {{held->key(), 7.0f, 0.0f},
                                                 {held->key(), 6.0f, 1.0f}};
  absl::StatusOr<RewardsResult> again = engine_->UpdateRewards("f1", twice);
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->updated, 1u);
  EXPECT_FLOAT_EQ(engine_->GetTraces("f1", keys)->traces[0].reward_internal,
                  1.0f);
  const std::vector<core::RewardUpdate> restore = {
      {held->key(), 1000.0f, 5.0f}};
  ASSERT_TRUE(engine_->UpdateRewards("f1", restore).ok());
  const std::vector<core::RewardUpdate> bad = {{held->key(), 1.0f, 1.0f},
                                               {held->key(), -3.0f, 1.0f}};
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->UpdateRewards("f1", bad).status()));
  EXPECT_FLOAT_EQ(engine_->GetTraces("f1", keys)->traces[0].reward, 1005.0f);
}

// A fleet whose settings name its own index kind gets its index from the
// fleet factory: made at creation, at a restart, and when its index
// snapshot is loaded (the snapshot records the kind); the other fleets'
// from the server's factory.
TEST_F(ManageTest, AFleetsOwnIndexKindIsMadeAndReloadedAsSuch) {
  std::vector<std::pair<int, int>> made;  // (kind, M) per fleet index made
  options_.fleet_index_factory = [&made](size_t dimension,
                                         const IndexSettings& index) {
    made.emplace_back(static_cast<int>(index.kind), index.hnsw_m);
    return index::NewExactIndex(dimension);
  };
  engine_ = OpenOn(options_, store_.get());
  ASSERT_NE(engine_, nullptr);
  CreateFleetRecord create;
  create.code_dimension = kDimension;
  create.settings.memory = options_.memory;
  create.settings.index.kind = IndexSettings::Kind::kHnsw;
  create.settings.index.hnsw_m = 24;
  MustUpload(MakeTraces("r1", 1, 40, rng_));  // "f1": the server's index
  std::vector<core::MemoryTrace> own = MakeTraces("r1", 1, 40, rng_);
  create.encoder_version = own.front().encoder_version;
  ASSERT_TRUE(engine_->CreateFleet("own", create).ok());
  for (size_t i = 0; i < own.size(); i += 20) {
    const std::span<const core::MemoryTrace> segment(own.data() + i, 20);
    absl::StatusOr<UploadResult> uploaded = engine_->Upload("own", segment);
    ASSERT_TRUE(uploaded.ok()) << uploaded.status();
  }
  ASSERT_EQ(made.size(), 1u);
  EXPECT_EQ(made[0], (std::pair<int, int>{2, 24}));
  EXPECT_EQ(engine_->GetFleet("own")->settings.index.hnsw_m, 24);
  CreateFleetRecord bad = create;
  bad.settings.index.hnsw_m = 1;
  EXPECT_TRUE(absl::IsInvalidArgument(engine_->CheckCreateFleet("other", bad)));

  // Reopened with its snapshot: the fleet's kind again, twice (the index
  // the snapshot loads into, and the one started before it).
  ASSERT_TRUE(engine_->SaveIndexSnapshots().ok());
  const FleetStats own_before = Stats("own");
  engine_.reset();
  made.clear();
  engine_ = OpenOn(options_, store_.get());
  ASSERT_NE(engine_, nullptr);
  ASSERT_FALSE(made.empty());
  for (const auto& [kind, m] : made) {
    EXPECT_EQ(kind, 2);
    EXPECT_EQ(m, 24);
  }
  ExpectSameStats(Stats("own"), own_before);
}

// A fleet that names only its graph codes (the server's index kind) also
// gets its index from the fleet factory, which learns the codes; so again
// after a restart (the setting is stored with the fleet).
TEST_F(ManageTest, AFleetsOwnGraphCodesReachTheFleetFactory) {
  std::vector<IndexSettings> made;
  options_.fleet_index_factory = [&made](size_t dimension,
                                         const IndexSettings& index) {
    made.push_back(index);
    return index::NewExactIndex(dimension);
  };
  engine_ = OpenOn(options_, store_.get());
  ASSERT_NE(engine_, nullptr);
  CreateFleetRecord create;
  create.code_dimension = kDimension;
  create.settings.memory = options_.memory;
  create.settings.index.hnsw_codes = IndexSettings::Codes::kFloat;
  std::vector<core::MemoryTrace> own = MakeTraces("r1", 1, 20, rng_);
  create.encoder_version = own.front().encoder_version;
  ASSERT_TRUE(engine_->CreateFleet("floats", create).ok());
  ASSERT_TRUE(engine_->Upload("floats", own).ok());
  ASSERT_EQ(made.size(), 1u);
  EXPECT_EQ(made[0].kind, IndexSettings::Kind::kServer);
  EXPECT_EQ(made[0].hnsw_codes, IndexSettings::Codes::kFloat);
  engine_.reset();
  made.clear();
  engine_ = OpenOn(options_, store_.get());
  ASSERT_NE(engine_, nullptr);
  ASSERT_FALSE(made.empty());
  for (const IndexSettings& index : made) {
    EXPECT_EQ(index.hnsw_codes, IndexSettings::Codes::kFloat);
  }
  EXPECT_EQ(engine_->GetFleet("floats")->settings.index.hnsw_codes,
            IndexSettings::Codes::kFloat);
}

TEST_F(ManageTest, GetTracesAnswersInTheOrderNamedAndListsTheMissing) {
  Fill();
  const std::vector<core::TraceKey> keys = {
      {"r2", 43}, {"r1", 1}, {"r7", 1}, {"r2", 43}, {"r1", 999}};
  absl::StatusOr<TraceLookup> lookup = engine_->GetTraces("f1", keys);
  ASSERT_TRUE(lookup.ok()) << lookup.status();
  std::vector<core::TraceKey> found;
  for (const core::MemoryTrace& trace : lookup->traces) {
    found.push_back(trace.key());
    EXPECT_EQ(trace.code.size(), kDimension);
  }
  // r1's seq 1 may have been downsampled: found or missing, never both.
  const bool r1_held = found.size() == 2;
  EXPECT_EQ(found.front(), (core::TraceKey{"r2", 43}));
  EXPECT_EQ(lookup->missing.size(), r1_held ? 2u : 3u);
  EXPECT_EQ(lookup->missing.back(), (core::TraceKey{"r1", 999}));
  EXPECT_TRUE(absl::IsInvalidArgument(
      engine_->GetTraces("f1", std::vector<core::TraceKey>{}).status()));
  EXPECT_TRUE(absl::IsNotFound(engine_->GetTraces("f0", keys).status()));
  const std::vector<core::TraceKey> bad = {{"a b", 1}};
  EXPECT_TRUE(absl::IsInvalidArgument(engine_->GetTraces("f1", bad).status()));
}

}  // namespace
}  // namespace fleetmem::engine

namespace fleetmem::engine {
namespace {

CreateFleetRecord Created(uint32_t dimension, int max_clusters,
                          int max_traces_per_cluster) {
  CreateFleetRecord create;
  create.code_dimension = dimension;
  create.encoder_version = "v1";
  create.settings.place_unit = "m";
  create.settings.memory = SmallOptions().memory;
  create.settings.memory.max_clusters = max_clusters;
  create.settings.memory.max_traces_per_cluster = max_traces_per_cluster;
  return create;
}

// Two fleets of other dimensions and bounds on one engine each hold their
// own, across a reopen; an update's smaller bound applies at the next
// consolidation; a fleet made by its first upload follows the server's.
TEST_F(ManageTest, FleetsKeepTheirOwnSettings) {
  ASSERT_TRUE(engine_->CreateFleet("small", Created(kDimension, 2, 2)).ok());
  ASSERT_TRUE(engine_->CreateFleet("wide", Created(16, 8, 4)).ok());
  EXPECT_TRUE(absl::IsFailedPrecondition(
      engine_->CreateFleet("wide", Created(16, 8, 4))));
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->CreateFleet("bad", Created(16, 0, 4))));
  EXPECT_TRUE(absl::IsNotFound(engine_->GetFleet("bad").status()));
  // Made and empty: it exists, with its shape.
  absl::StatusOr<FleetInfo> wide = engine_->GetFleet("wide");
  ASSERT_TRUE(wide.ok()) << wide.status();
  EXPECT_EQ(wide->shape.code_dimension, 16u);
  EXPECT_TRUE(wide->own_settings);
  EXPECT_EQ(wide->settings.place_unit, "m");
  EXPECT_EQ(Stats("wide").traces, 0u);
  // Another dimension is refused by the fleet's shape.
  EXPECT_FALSE(engine_->Upload("wide", MakeTraces("r1", 1, 5, rng_)).ok());

  for (int segment = 0; segment < 6; ++segment) {
    MustUpload(MakeTraces("r1", 1 + 20 * segment, 20, rng_), "small");
    std::vector<core::MemoryTrace> traces;
    for (uint64_t seq = 1 + 20 * segment; seq <= 20 + 20 * segment; ++seq) {
      traces.push_back(MakeTrace("r1", seq, rng_, 1.0f, 16));
    }
    MustUpload(traces, "wide");
    MustUpload(MakeTraces("r1", 1 + 20 * segment, 20, rng_), "f1");
  }
  EXPECT_LE(Stats("small").clusters, 2u);
  EXPECT_LE(Stats("wide").clusters, 8u);
  EXPECT_GT(Stats("wide").clusters, 2u);
  EXPECT_EQ(Stats("small").max_clusters, 2u);
  EXPECT_EQ(Stats("f1").max_clusters,
            static_cast<uint32_t>(options_.memory.max_clusters));
  EXPECT_FALSE(engine_->GetFleet("f1")->own_settings);

  // A smaller K_max for "wide": held until the next consolidation.
  FleetSettingsUpdate update;
  update.max_clusters = 3;
  update.replay_decay = 0.5;
  update.refresh_pair_radius = 12.5;
  update.refresh_uniform = true;
  absl::StatusOr<FleetSettings> after = engine_->UpdateFleet("wide", update);
  ASSERT_TRUE(after.ok()) << after.status();
  EXPECT_EQ(after->memory.max_clusters, 3);
  EXPECT_EQ(after->memory.max_traces_per_cluster, 4);  // unchanged
  std::vector<core::MemoryTrace> more;
  for (uint64_t seq = 121; seq <= 140; ++seq) {
    more.push_back(MakeTrace("r1", seq, rng_, 1.0f, 16));
  }
  MustUpload(more, "wide");
  EXPECT_LE(Stats("wide").clusters, 3u);
  FleetSettingsUpdate bad;
  bad.max_clusters = 0;
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->UpdateFleet("wide", bad).status()));
  bad = FleetSettingsUpdate();
  bad.refresh_pair_radius = -1.0;
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->UpdateFleet("wide", bad).status()));

  engine_.reset();
  engine_ = OpenEngine();
  wide = engine_->GetFleet("wide");
  ASSERT_TRUE(wide.ok());
  EXPECT_EQ(wide->settings.memory.max_clusters, 3);
  EXPECT_EQ(wide->settings.memory.replay_decay, 0.5);
  EXPECT_EQ(wide->settings.memory.refresh_pair_radius, 12.5);
  EXPECT_TRUE(wide->settings.memory.refresh_uniform);
  EXPECT_EQ(engine_->GetFleet("small")->settings.memory.refresh_pair_radius,
            0.0);
  EXPECT_EQ(Stats("small").max_clusters, 2u);
  EXPECT_EQ(Stats("small").max_traces_per_cluster, 2u);
  EXPECT_LE(Stats("wide").clusters, 3u);
  // An entry applied again changes nothing.
  update.max_clusters = 7;
  ASSERT_TRUE(engine_->UpdateFleet("wide", update, 50).ok());
  update.max_clusters = 5;
  EXPECT_EQ(engine_->UpdateFleet("wide", update, 50)->memory.max_clusters, 7);
}

}  // namespace
}  // namespace fleetmem::engine

namespace fleetmem::engine {
namespace {

// Retention deletes what is older than max_age and each robot's oldest
// beyond its newest max_traces_per_robot, as of the record's clock, as a
// delete (events, counts, a reopen); a fleet without retention keeps all.
TEST_F(ManageTest, RetentionDeletesByAgeAndPerRobot) {
  Fill();  // timestamps 1,000 ns x seq
  const FleetStats before = Stats();
  absl::StatusOr<DeleteResult> none =
      engine_->EnforceRetention("f1", 1'000'000'000'000);
  ASSERT_TRUE(none.ok()) << none.status();
  EXPECT_EQ(none->deleted, 0u);  // the server's settings: no retention

  uint64_t hook_deleted = 0;
  engine_.reset();
  engine_ = OpenEngine({.on_retention = [&](std::string_view, uint64_t n) {
    hook_deleted += n;
  }});
  // Each robot's held seqs, newest first.
  const auto held_seqs = [&] {
    std::map<std::string, std::vector<uint64_t>> seqs;
    absl::StatusOr<TracePage> page =
        engine_->ListTraces("f1", std::nullopt, 500);
    EXPECT_TRUE(page.ok());
    for (const core::MemoryTrace& trace : page->traces) {
      seqs[trace.robot_id].push_back(trace.seq);
    }
    for (auto& [robot, list] : seqs) {
      std::sort(list.rbegin(), list.rend());
    }
    return seqs;
  };
  std::map<std::string, std::vector<uint64_t>> newest = held_seqs();
  for (auto& [robot, list] : newest) {
    if (list.size() > 10) list.resize(10);
  }
  FleetSettingsUpdate update;
  update.max_traces_per_robot = 10;
  ASSERT_TRUE(engine_->UpdateFleet("f1", update).ok());
  absl::StatusOr<DeleteResult> per_robot = engine_->EnforceRetention("f1", 0);
  ASSERT_TRUE(per_robot.ok()) << per_robot.status();
  EXPECT_GT(per_robot->deleted, 0u);
  EXPECT_EQ(hook_deleted, per_robot->deleted);
  const FleetStats after = Stats();
  for (const RobotStats& robot : after.robots) {
    EXPECT_LE(robot.traces + robot.pending_traces, 10u) << robot.robot_id;
  }
  // Each robot kept its newest ten of what the fleet held.
  EXPECT_EQ(held_seqs(), newest);

  // By age: max_age 1 s, as of a clock 1 s and 44,000 ns past the epoch
  // (the traces' times are 1,000 ns x seq): those before 44,000 ns go.
  FleetSettingsUpdate age;
  age.max_age_seconds = 1;
  age.max_traces_per_robot = 0;
  ASSERT_TRUE(engine_->UpdateFleet("f1", age).ok());
  const int64_t now_ns = 1'000'000'000 + 44'000;
  absl::StatusOr<DeleteResult> by_age = engine_->EnforceRetention("f1", now_ns);
  ASSERT_TRUE(by_age.ok());
  absl::StatusOr<TracePage> page = engine_->ListTraces("f1", std::nullopt, 500);
  ASSERT_TRUE(page.ok());
  ASSERT_FALSE(page->traces.empty());
  for (const core::MemoryTrace& trace : page->traces) {
    EXPECT_GE(trace.timestamp_ns, 44'000) << trace.robot_id << trace.seq;
  }
  EXPECT_LT(Stats().traces + Stats().pending_traces,
            before.traces + before.pending_traces);
  engine_.reset();
  engine_ = OpenEngine();
  page = engine_->ListTraces("f1", std::nullopt, 500);
  ASSERT_TRUE(page.ok());
  for (const core::MemoryTrace& trace : page->traces) {
    EXPECT_GE(trace.timestamp_ns, 44'000);
  }
}

}  // namespace
}  // namespace fleetmem::engine

namespace fleetmem::engine {
namespace {

// Many codes in one query: each answered as it would be alone, in order,
// under one read; the count and the shared byte budget are bounded.
// A filtered replay draws among the matching traces only, with their
// weights; a logged one is the same on every replica (seeded by its entry).
TEST_F(ManageTest, AFilteredReplayDrawsOnlyWhatPassesTheFilter) {
  Fill();
  core::ReadFilter only_r2;
  only_r2.robot_ids = {"r2"};
  const uint64_t r2_static = FindRobot(Stats(), "r2")->traces;
  ASSERT_GT(r2_static, 0u);
  absl::StatusOr<std::vector<core::MemoryTrace>> drawn =
      engine_->SampleReplay("f1", "reader", 100, "", 0, &only_r2);
  ASSERT_TRUE(drawn.ok()) << drawn.status();
  EXPECT_EQ(drawn->size(), r2_static);  // every one, none twice
  std::set<uint64_t> seqs;
  for (const core::MemoryTrace& trace : *drawn) {
    EXPECT_EQ(trace.robot_id, "r2");
    seqs.insert(trace.seq);
  }
  EXPECT_EQ(seqs.size(), drawn->size());
  core::ReadFilter nobody;
  nobody.domains = {"nowhere"};
  EXPECT_TRUE(
      engine_->SampleReplay("f1", "reader", 5, "", 0, &nobody)->empty());
  core::ReadFilter bad;
  bad.time_from_ns = 5;
  bad.time_to_ns = 5;
  EXPECT_TRUE(absl::IsInvalidArgument(
      engine_->SampleReplay("f1", "reader", 5, "", 0, &bad).status()));

  // As a log entry (seeded by it): the same filter holds.
  absl::StatusOr<std::vector<core::MemoryTrace>> logged =
      engine_->SampleReplay("f1", "reader", 3, "", 900, &only_r2);
  ASSERT_TRUE(logged.ok()) << logged.status();
  ASSERT_EQ(logged->size(), 3u);
  for (const core::MemoryTrace& trace : *logged) {
    EXPECT_EQ(trace.robot_id, "r2");
  }
}

TEST_F(ManageTest, ManyCodesInOneQueryAnswerAsEachAlone) {
  Fill();
  absl::StatusOr<TracePage> page = engine_->ListTraces("f1", std::nullopt, 500);
  ASSERT_TRUE(page.ok());
  PlaceQuery query;
  query.code = page->traces[0].code;
  query.k = 3;
  std::vector<std::vector<float>> more;
  for (size_t i = 1; i < 6; ++i) more.push_back(page->traces[i].code);
  absl::StatusOr<std::vector<std::vector<PlaceMatch>>> answers =
      engine_->QueryPlaces("f1", query, more);
  ASSERT_TRUE(answers.ok()) << answers.status();
  ASSERT_EQ(answers->size(), 6u);
  for (size_t i = 0; i < 6; ++i) {
    PlaceQuery alone = query;
    alone.code = page->traces[i].code;
    absl::StatusOr<std::vector<PlaceMatch>> one =
        engine_->QueryPlace("f1", alone);
    ASSERT_TRUE(one.ok());
    ASSERT_EQ((*answers)[i].size(), one->size());
    for (size_t j = 0; j < one->size(); ++j) {
      EXPECT_EQ((*answers)[i][j].trace.key(), (*one)[j].trace.key());
      EXPECT_EQ((*answers)[i][j].distance, (*one)[j].distance);
    }
    EXPECT_EQ((*answers)[i][0].trace.key(), page->traces[i].key());
  }
  more.push_back(std::vector<float>(kDimension + 1, 1.0f));
  absl::Status wrong = engine_->QueryPlaces("f1", query, more).status();
  EXPECT_TRUE(absl::IsInvalidArgument(wrong));
  EXPECT_NE(wrong.message().find("codes[6]"), std::string::npos) << wrong;
  std::vector<std::vector<float>> too_many(options_.max_query_codes,
                                           query.code);
  EXPECT_TRUE(absl::IsInvalidArgument(
      engine_->QueryPlaces("f1", query, too_many).status()));
}

}  // namespace
}  // namespace fleetmem::engine

namespace fleetmem::engine {
namespace {

// A query's filter: every match passes it, and the matches are the nearest
// of the traces that pass (the exact index: the filtered answer is exact).
TEST_F(ManageTest, AFilteredQueryReturnsOnlyWhatPassesTheFilter) {
  Fill();
  absl::StatusOr<TracePage> page = engine_->ListTraces("f1", std::nullopt, 500);
  ASSERT_TRUE(page.ok());
  PlaceQuery query;
  query.code = page->traces.front().code;  // r1's
  query.k = 5;
  query.filter.robot_ids = {"r2"};
  query.filter.domains = {"winter"};
  absl::StatusOr<std::vector<PlaceMatch>> matches =
      engine_->QueryPlace("f1", query);
  ASSERT_TRUE(matches.ok()) << matches.status();
  ASSERT_FALSE(matches->empty());
  std::vector<float> distances;
  for (const core::MemoryTrace& trace : page->traces) {
    if (query.filter.Matches(trace)) {
      distances.push_back(core::CodeDistance(query.code, trace.code));
    }
  }
  std::sort(distances.begin(), distances.end());
  ASSERT_EQ(matches->size(), std::min<size_t>(5, distances.size()));
  for (size_t i = 0; i < matches->size(); ++i) {
    EXPECT_EQ((*matches)[i].trace.robot_id, "r2");
    EXPECT_EQ((*matches)[i].trace.domain, "winter");
    EXPECT_NEAR((*matches)[i].distance, distances[i], 1e-5);
  }
  query.filter.time_from_ns = 5;
  query.filter.time_to_ns = 5;
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->QueryPlace("f1", query).status()));
  query.filter = {};
  query.filter.robot_ids = {"bad id"};
  EXPECT_TRUE(
      absl::IsInvalidArgument(engine_->QueryPlace("f1", query).status()));
}

// Counts the put clusters' and updates' traces that reach the store
// without their codes.
class CodelessCountingStore : public ForwardingStore {
 public:
  using ForwardingStore::ForwardingStore;
  absl::Status Apply(std::string_view fleet_id,
                     const FleetMutation& mutation) override {
    for (const core::Cluster& cluster : mutation.put_clusters) {
      for (const core::MemoryTrace& trace : cluster.traces) {
        if (trace.code.empty()) ++codeless_clustered;
      }
    }
    for (const core::MemoryTrace& trace : mutation.update_traces) {
      if (trace.code.empty()) ++codeless_updated;
    }
    return ForwardingStore::Apply(fleet_id, mutation);
  }
  int codeless_clustered = 0;
  int codeless_updated = 0;
};

// Merges of forgetting, a delete that leaves a cluster some of its traces
// and a reward update write the traces they keep without the codes memory
// dropped (no code read back from the index): the store keeps what it
// holds, each code the one uploaded, across a restart too.
TEST_F(MemoryEngineTest, MergesDeletesAndRewardsKeepEveryStoredCode) {
  CodelessCountingStore counting(store_.get());
  // The engine on `counting` stops before `counting` goes, whatever fails.
  struct StopFirst {
    std::unique_ptr<MemoryEngine>& engine;
    ~StopFirst() { engine.reset(); }
  } stop_first{engine_};
  engine_.reset();
  engine_ = OpenOn(options_, &counting);
  ASSERT_NE(engine_, nullptr);
  std::map<core::TraceKey, std::vector<float>> uploaded;
  for (int segment = 0; segment < 8; ++segment) {
    const std::string robot = segment % 2 == 0 ? "r1" : "r2";
    const std::vector<core::MemoryTrace> traces =
        MakeTraces(robot, 1 + 20 * (segment / 2), 20, rng_);
    for (const core::MemoryTrace& trace : traces) {
      uploaded[trace.key()] = trace.code;
    }
    MustUpload(traces);
  }
  EXPECT_GT(Stats().clusters_forgotten, 0u);  // merged (merge_on_forget)
  EXPECT_GT(counting.codeless_clustered, 0);

  const std::vector<core::MemoryTrace> held = AllTraces(*engine_, "f1", 200);
  std::map<uint64_t, std::vector<core::TraceKey>> members;
  for (const core::MemoryTrace& trace : held) {
    members[trace.cluster_id].push_back(trace.key());
  }
  auto shared = std::find_if(members.begin(), members.end(),
                             [](const auto& m) { return m.second.size() > 1; });
  ASSERT_NE(shared, members.end());
  const core::TraceKey gone = shared->second.front();
  const core::TraceKey rewarded = shared->second.back();
  const int clustered_before = counting.codeless_clustered;
  core::TraceFilter one;
  one.robot_id = gone.robot_id;
  one.seq_first = one.seq_last = gone.seq;
  absl::StatusOr<DeleteResult> deleted = engine_->DeleteTraces("f1", one);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_EQ(deleted->deleted, 1u);
  EXPECT_EQ(deleted->clusters_changed, 1u);
  EXPECT_GT(counting.codeless_clustered, clustered_before);
  const std::vector<core::RewardUpdate> updates = {{rewarded, 2.0f, 0.5f}};
  absl::StatusOr<RewardsResult> rescored =
      engine_->UpdateRewards("f1", updates);
  ASSERT_TRUE(rescored.ok()) << rescored.status();
  EXPECT_EQ(rescored->updated, 1u);
  EXPECT_EQ(counting.codeless_updated, 1);

  absl::StatusOr<FleetRecord> stored = store_->LoadFleet("f1");
  ASSERT_TRUE(stored.ok()) << stored.status();
  size_t traces = 0;
  for (const core::Cluster& cluster : stored->clusters) {
    for (const core::MemoryTrace& trace : cluster.traces) {
      ++traces;
      EXPECT_NE(trace.key(), gone);
      EXPECT_EQ(trace.code, uploaded.at(trace.key()))
          << trace.robot_id << "/" << trace.seq;
      if (trace.key() == rewarded) EXPECT_EQ(trace.reward, 2.5f);
    }
  }
  EXPECT_EQ(traces, held.size() - 1);

  engine_.reset();
  engine_ = OpenEngine();
  ASSERT_NE(engine_, nullptr);
  const std::vector<core::MemoryTrace> reopened =
      AllTraces(*engine_, "f1", 200);
  EXPECT_EQ(reopened.size(), held.size() - 1);
  for (const core::MemoryTrace& trace : reopened) {
    EXPECT_EQ(trace.code, uploaded.at(trace.key()));
  }
}

}  // namespace
}  // namespace fleetmem::engine
