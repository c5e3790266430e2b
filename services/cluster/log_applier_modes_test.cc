// The same applier tests over both modes' logs, through the one log port
// (engine::FleetLog): embedded mode's local segment log applied by
// engine::WritePath's appliers, and distributed mode's JetStream log (a
// real nats-server) applied by the fleet's owner, cluster::Materialiser.
// Both run the one engine::LogApplier; these tests hold what a user of
// either mode relies on: the log applied is the memory of the same uploads
// made directly, calls are applied in the log's order, an entry the
// fleet's state refuses is passed alike, a store error stops the apply
// until the entry applies, and an applier started again applies only the
// rest.
#include <memory>
#include <string>
#include <vector>

#include "absl/time/clock.h"
#include "gtest/gtest.h"
#include "services/cluster/materialiser.h"
#include "services/cluster/testing/cluster_test_util.h"
#include "services/cluster/testing/nats_fixture.h"
#include "services/engine/fleet_log.h"
#include "services/engine/write_path.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_store.h"
#include "services/storage/segment_log.h"
#include "services/testing/memory_engine_test_util.h"

namespace fleetmem::cluster {
namespace {

using testing_util::ExpectSameState;
using testing_util::State;
using testing_util::StateOf;
using testing_util::Uploads;

constexpr char kFleet[] = "fleet-m";

// One mode's log of a fleet (the one log port, engine::FleetLog) and its
// applier.
class Mode {
 public:
  virtual ~Mode() = default;
  virtual engine::FleetLog& log() = 0;
  // Appends an upload to the fleet's log, as the receiving replica or the
  // write path does (admission is not the subject here: a test may log
  // what admission would refuse).
  void Append(const std::vector<core::MemoryTrace>& traces,
              const std::string& id = "") {
    ASSERT_TRUE(testing_util::AppendUpload(log(), kFleet, traces, id).ok());
  }
  // Appends a call's record.
  void AppendCall(const engine::LogRecord& record) {
    const engine::LogAppend append{record};
    ASSERT_TRUE(log().Append(kFleet, {&append, 1}, {}).ok());
  }
  // Starts the mode's applier over `engine` and applies the fleet's log
  // through its end: OK, or the error the apply stopped at.
  virtual absl::Status ApplyAll(engine::MemoryEngine& engine) = 0;
};

// Embedded mode: the local segment log; a WritePath opened over it
// recovers and applies its tail.
class EmbeddedMode : public Mode {
 public:
  explicit EmbeddedMode(std::unique_ptr<storage::SegmentLog> log)
      : log_(std::move(log)) {}
  engine::FleetLog& log() override { return *log_; }
  absl::Status ApplyAll(engine::MemoryEngine& engine) override {
    absl::StatusOr<std::unique_ptr<engine::WritePath>> path =
        engine::WritePath::Open(
            {.appliers = 1, .retry_interval = absl::Milliseconds(20)}, &engine,
            log_.get());
    if (!path.ok()) return path.status();
    return (*path)->WaitAppliedAll(kFleet, absl::Now() + absl::Seconds(30));
  }

 private:
  std::unique_ptr<storage::SegmentLog> log_;
};

// Distributed mode: the fleet's JetStream log; a Materialiser (replica
// "a", its lease on the fleet) catches up with it.
class DistributedMode : public Mode {
 public:
  explicit DistributedMode(std::unique_ptr<NatsFleetLog> log)
      : log_(std::move(log)) {}
  engine::FleetLog& log() override { return *log_; }
  absl::Status ApplyAll(engine::MemoryEngine& engine) override {
    Materialiser materialiser({.replica_id = "replica-a"}, log_.get(),
                              log_.get(), /*snapshots=*/nullptr, &engine);
    return materialiser.CatchUp(kFleet).status();
  }

 private:
  std::unique_ptr<NatsFleetLog> log_;
};

class LogApplierModesTest : public NatsFixture,
                            public ::testing::WithParamInterface<bool> {
 protected:
  void SetUp() override {
    NatsFixture::SetUp();
    if (GetParam()) {
      std::unique_ptr<NatsFleetLog> log = Connect();
      ASSERT_NE(log, nullptr);
      mode_ = std::make_unique<DistributedMode>(std::move(log));
    } else {
      absl::StatusOr<std::unique_ptr<storage::SegmentLog>> log =
          storage::SegmentLog::Open({.directory = dir_.Join("ingest-log")});
      ASSERT_TRUE(log.ok()) << log.status();
      mode_ = std::make_unique<EmbeddedMode>(*std::move(log));
    }
  }
  // An engine over `store` (this replica's, restarted by opening again).
  std::unique_ptr<engine::MemoryEngine> Open(engine::MemoryStore* store) {
    absl::StatusOr<std::unique_ptr<engine::MemoryEngine>> opened =
        engine::MemoryEngine::Open(
            testing_util::SmallOptions(), store,
            [](size_t dimension) { return index::NewExactIndex(dimension); });
    EXPECT_TRUE(opened.ok()) << opened.status();
    return opened.ok() ? *std::move(opened) : nullptr;
  }
  // The memory of `uploads` made directly (no log).
  State Direct(const std::vector<std::vector<core::MemoryTrace>>& uploads) {
    testing_util::Replica direct;
    for (const std::vector<core::MemoryTrace>& batch : uploads) {
      EXPECT_TRUE(direct.engine->Upload(kFleet, batch).ok());
    }
    return StateOf(*direct.engine, kFleet);
  }

  std::unique_ptr<Mode> mode_;
  std::unique_ptr<engine::MemoryStore> store_ = storage::NewInMemoryStore();
};

TEST_P(LogApplierModesTest, TheLogAppliedIsTheMemoryOfTheUploadsMadeDirectly) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  for (const auto& batch : uploads) mode_->Append(batch);
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  const State want = Direct(uploads);
  ASSERT_GT(want.stats.consolidations, 0u);
  ASSERT_GT(want.stats.clusters_forgotten, 0u);
  ExpectSameState(StateOf(*engine, kFleet), want);
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), uploads.size());
}

TEST_P(LogApplierModesTest, AnEntryTheFleetsStateRefusesIsPassedAlike) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  std::vector<core::MemoryTrace> wrong = uploads[1];
  for (core::MemoryTrace& trace : wrong) trace.code.resize(4);
  for (const auto& batch : {uploads[0], wrong, uploads[2]}) {
    mode_->Append(batch);
  }
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  ExpectSameState(StateOf(*engine, kFleet), Direct({uploads[0], uploads[2]}));
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), 3u);
}

// Calls whose effect replicas must agree on are entries too, applied in
// the log's order: a Consolidate between uploads, and a SampleReplay drawn
// under its entry's sequence, counted once.
TEST_P(LogApplierModesTest, CallsAreAppliedInTheLogsOrder) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  for (size_t i = 0; i < 3; ++i) mode_->Append(uploads[i]);
  mode_->AppendCall(engine::ConsolidateRecord{});
  mode_->AppendCall(engine::SampleReplayRecord{"r1", 6, "req-1"});
  mode_->Append(uploads[3]);
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), 6u);

  testing_util::Replica direct;
  for (size_t i = 0; i < 3; ++i) {
    ASSERT_TRUE(direct.engine->Upload(kFleet, uploads[i], i + 1).ok());
  }
  ASSERT_TRUE(direct.engine->Consolidate(kFleet).ok());
  absl::StatusOr<std::vector<core::MemoryTrace>> sample =
      direct.engine->SampleReplay(kFleet, "r1", 6, "req-1", 5);
  ASSERT_TRUE(sample.ok()) << sample.status();
  ASSERT_EQ(sample->size(), 6u);
  ASSERT_TRUE(direct.engine->Upload(kFleet, uploads[3], 6).ok());
  const State want = StateOf(*direct.engine, kFleet);
  ExpectSameState(StateOf(*engine, kFleet), want);
  EXPECT_EQ(StateOf(*engine, kFleet).stats.robots.front().replayed, 6u);
}

// DeleteTraces and UpdateRewards are entries too: logged between uploads
// they remove and re-score what was uploaded before them, in both modes
// (the records travel through each log's encoding), and the memory equals
// the same calls made directly at the same positions.
TEST_P(LogApplierModesTest, DeletesAndRewardsAreAppliedInTheLogsOrder) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  ASSERT_GE(uploads.size(), 4u);
  for (size_t i = 0; i < 3; ++i) mode_->Append(uploads[i]);
  core::TraceFilter filter;
  filter.robot_id = uploads[0].front().robot_id;
  filter.seq_first = uploads[0].front().seq;
  filter.seq_last = uploads[0].front().seq + 4;
  filter.time_to_ns = 1;  // the traces' are 0
  mode_->AppendCall(engine::DeleteTracesRecord{filter});
  const std::vector<core::RewardUpdate> rewards = {
      {uploads[1].front().key(), 7.5f, 0.25f},
      {uploads[2].back().key(), 0.0f, 3.0f},
      {core::TraceKey{"nobody", 1}, 1.0f, 1.0f}};
  mode_->AppendCall(engine::UpdateRewardsRecord{rewards});
  mode_->Append(uploads[3]);
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), 6u);

  testing_util::Replica direct;
  for (size_t i = 0; i < 3; ++i) {
    ASSERT_TRUE(direct.engine->Upload(kFleet, uploads[i], i + 1).ok());
  }
  absl::StatusOr<engine::DeleteResult> deleted =
      direct.engine->DeleteTraces(kFleet, filter, 4);
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  ASSERT_GT(deleted->deleted, 0u);
  absl::StatusOr<engine::RewardsResult> rescored =
      direct.engine->UpdateRewards(kFleet, rewards, 5);
  ASSERT_TRUE(rescored.ok()) << rescored.status();
  ASSERT_TRUE(direct.engine->Upload(kFleet, uploads[3], 6).ok());
  ExpectSameState(StateOf(*engine, kFleet), StateOf(*direct.engine, kFleet));
  const std::vector<core::TraceKey> keys = {rewards[0].key, rewards[1].key};
  absl::StatusOr<engine::TraceLookup> logged = engine->GetTraces(kFleet, keys);
  absl::StatusOr<engine::TraceLookup> made =
      direct.engine->GetTraces(kFleet, keys);
  ASSERT_TRUE(logged.ok() && made.ok());
  ASSERT_EQ(logged->traces.size(), made->traces.size());
  for (size_t i = 0; i < made->traces.size(); ++i) {
    EXPECT_EQ(logged->traces[i].reward, made->traces[i].reward);
    EXPECT_EQ(logged->traces[i].reward_internal,
              made->traces[i].reward_internal);
  }
}

// A filtered SampleReplay travels with its filter through both logs: only
// the filtered robot's traces are drawn (their replay counts show it).
TEST_P(LogApplierModesTest, AFilteredSampleKeepsItsFilterThroughTheLog) {
  for (const auto& batch : Uploads()) mode_->Append(batch);
  core::ReadFilter only_r2;
  only_r2.robot_ids = {"r2"};
  mode_->AppendCall(engine::SampleReplayRecord{"r1", 10, "req-f", &only_r2});
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  int drawn = 0;
  int r2_held = 0;  // in the static memory: what a sample draws from
  for (const auto& [robot, seq, cluster, replays] :
       StateOf(*engine, kFleet).traces) {
    if (robot == "r2" && cluster != 0) ++r2_held;
    if (replays == 0) continue;
    EXPECT_EQ(robot, "r2") << seq;
    ++drawn;
  }
  ASSERT_GT(r2_held, 0);
  EXPECT_EQ(drawn, std::min(r2_held, 10));
}

// DeleteFleet is an entry too: the uploads before it leave with the
// fleet; those after it make the fleet anew, in both modes.
TEST_P(LogApplierModesTest, ADeleteFleetEntryRemakesTheFleetFromWhatFollows) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  ASSERT_GE(uploads.size(), 4u);
  for (size_t i = 0; i < 3; ++i) mode_->Append(uploads[i]);
  mode_->AppendCall(engine::DeleteFleetRecord{});
  // The same seqs again, new to the new fleet (under another id, as the
  // write path tags the entries after a delete).
  mode_->Append(uploads[0], "d4/again");
  mode_->Append(uploads[3]);
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), 6u);
  const State want = Direct({uploads[0], uploads[3]});
  const State got = StateOf(*engine, kFleet);
  EXPECT_EQ(got.stats.traces + got.stats.pending_traces,
            want.stats.traces + want.stats.pending_traces);
  EXPECT_EQ(got.stats.robots.size(), want.stats.robots.size());
}

// A fleet made by CreateFleet as its log's first entry, an UpdateFleet
// between uploads and a retention call: both logs carry every setting,
// and the memory is the same calls made directly.
TEST_P(LogApplierModesTest, AFleetsSettingsTravelThroughTheLog) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  engine::CreateFleetRecord create;
  create.code_dimension = 8;
  create.encoder_version = "enc-v1";
  create.settings.place_unit = "m";
  create.settings.memory = testing_util::SmallOptions().memory;
  create.settings.memory.max_clusters = 3;
  create.settings.memory.merge_on_forget = false;
  create.settings.max_traces_per_robot = 40;
  const engine::LogAppend first{create};
  ASSERT_TRUE(
      mode_->log().Append(kFleet, {&first, 1}, {.only_first = true}).ok());
  for (size_t i = 0; i < 6; ++i) mode_->Append(uploads[i]);
  engine::FleetSettingsUpdate update;
  update.max_clusters = 2;
  update.replay_decay = 0.75;
  mode_->AppendCall(engine::UpdateFleetRecord{update});
  for (size_t i = 6; i < uploads.size(); ++i) mode_->Append(uploads[i]);
  mode_->AppendCall(engine::EnforceRetentionRecord{5});
  std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
  ASSERT_NE(engine, nullptr);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());

  testing_util::Replica direct;
  uint64_t position = 1;
  ASSERT_TRUE(direct.engine->CreateFleet(kFleet, create, position).ok());
  for (size_t i = 0; i < 6; ++i) {
    ASSERT_TRUE(direct.engine->Upload(kFleet, uploads[i], ++position).ok());
  }
  ASSERT_TRUE(direct.engine->UpdateFleet(kFleet, update, ++position).ok());
  for (size_t i = 6; i < uploads.size(); ++i) {
    ASSERT_TRUE(direct.engine->Upload(kFleet, uploads[i], ++position).ok());
  }
  absl::StatusOr<engine::DeleteResult> retained =
      direct.engine->EnforceRetention(kFleet, 5, ++position);
  ASSERT_TRUE(retained.ok()) << retained.status();
  ExpectSameState(StateOf(*engine, kFleet), StateOf(*direct.engine, kFleet));
  for (const engine::RobotStats& robot :
       StateOf(*engine, kFleet).stats.robots) {
    EXPECT_LE(robot.traces + robot.pending_traces, 40u) << robot.robot_id;
  }
  absl::StatusOr<engine::FleetInfo> info = engine->GetFleet(kFleet);
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_TRUE(info->own_settings);
  EXPECT_EQ(info->settings.place_unit, "m");
  EXPECT_EQ(info->settings.memory.max_clusters, 2);
  EXPECT_EQ(info->settings.memory.replay_decay, 0.75);
  EXPECT_FALSE(info->settings.memory.merge_on_forget);
  EXPECT_EQ(info->settings.max_traces_per_robot, 40u);
  EXPECT_LE(StateOf(*engine, kFleet).stats.clusters, 2u);
}

// A full disk (RESOURCE_EXHAUSTED from the store) is never passed: the
// apply stops at the entry, and the entry applies once the store writes.
TEST_P(LogApplierModesTest, AStoreErrorStopsTheApplyUntilTheEntryApplies) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  engine::FlakyStore flaky(store_.get());
  std::unique_ptr<engine::MemoryEngine> engine = Open(&flaky);
  ASSERT_NE(engine, nullptr);
  mode_->Append(uploads[0]);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  mode_->Append(uploads[1]);
  mode_->Append(uploads[2]);
  flaky.fail_after = flaky.applies;
  flaky.failure = absl::ResourceExhaustedError("disk nearly full");
  EXPECT_EQ(mode_->ApplyAll(*engine).code(),
            absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), 1u);
  flaky.fail_after = -1;
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), 3u);
  ExpectSameState(StateOf(*engine, kFleet),
                  Direct({uploads[0], uploads[1], uploads[2]}));
}

// A replica restarted on its store applies the entries after the position
// it holds, none twice.
TEST_P(LogApplierModesTest, AnApplierStartedAgainAppliesOnlyTheRest) {
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  const size_t half = uploads.size() / 2;
  for (size_t i = 0; i < half; ++i) mode_->Append(uploads[i]);
  {
    std::unique_ptr<engine::MemoryEngine> engine = Open(store_.get());
    ASSERT_NE(engine, nullptr);
    ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  }
  for (size_t i = half; i < uploads.size(); ++i) mode_->Append(uploads[i]);
  engine::FlakyStore counted(store_.get());
  std::unique_ptr<engine::MemoryEngine> engine = Open(&counted);
  ASSERT_NE(engine, nullptr);
  ASSERT_EQ(engine->LogPosition(kFleet).value_or(0), half);
  ASSERT_TRUE(mode_->ApplyAll(*engine).ok());
  EXPECT_EQ(engine->LogPosition(kFleet).value_or(0), uploads.size());
  ExpectSameState(StateOf(*engine, kFleet), Direct(uploads));
  // Each applied entry writes once or twice (an upload, its consolidation
  // after it); none of the first half wrote again.
  EXPECT_LE(counted.applies, static_cast<int>(2 * (uploads.size() - half)));
}

INSTANTIATE_TEST_SUITE_P(BothModes, LogApplierModesTest, ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& info) {
                           return info.param ? "JetStreamLogMaterialiser"
                                             : "LocalLogWritePath";
                         });

}  // namespace
}  // namespace fleetmem::cluster
