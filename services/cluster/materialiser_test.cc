// The materialiser against a real nats-server: replicas that apply one
// fleet's log reach the memory the embedded mode reaches with the same
// uploads, a replica that stops renewing is fenced, and another takes over
// from the log alone.
#include "services/cluster/materialiser.h"

#include <chrono>
#include <random>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/cluster/testing/cluster_test_util.h"
#include "services/cluster/testing/nats_fixture.h"
#include "services/common/testing/manual_clock.h"
#include "services/storage/fleet_image.h"
#include "services/testing/memory_engine_test_util.h"

namespace fleetmem::cluster {
namespace {

using testing_util::AppendUpload;
using testing_util::AppendUploads;
using testing_util::ExpectSameState;
using testing_util::Replica;
using testing_util::State;
using testing_util::StateOf;
using testing_util::Uploads;

using MaterialiserTest = NatsFixture;

TEST_F(MaterialiserTest, ReplicasReachTheEmbeddedModesMemoryAndFailOver) {
  const std::string fleet = "fleet-a";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  Replica embedded;
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  for (const std::vector<core::MemoryTrace>& batch : uploads) {
    ASSERT_TRUE(embedded.engine->Upload(fleet, batch).ok());
    ASSERT_TRUE(AppendUpload(*log, fleet, batch).ok());
  }
  // A robot's retry with the same batch: JetStream drops it by its id.
  EXPECT_TRUE(AppendUpload(*log, fleet, uploads[4])->duplicate);
  // A retry cut differently (a new id): the replicas drop its traces by
  // (robot_id, seq), as the embedded mode does.
  std::vector<core::MemoryTrace> recut(uploads[4].begin() + 2,
                                       uploads[4].end());
  recut.insert(recut.end(), uploads[7].begin(), uploads[7].begin() + 3);
  ASSERT_TRUE(embedded.engine->Upload(fleet, recut).ok());
  ASSERT_TRUE(AppendUpload(*log, fleet, recut).ok());
  const State want = StateOf(*embedded.engine, fleet);
  ASSERT_GT(want.stats.consolidations, 0u);
  ASSERT_GT(want.stats.clusters_forgotten, 0u);

  Replica a, b;
  std::unique_ptr<NatsFleetLog> log_b = Connect();
  auto materialiser_a = std::make_unique<Materialiser>(
      MaterialiserOptions{.replica_id = "replica-a", .batch = 7}, log.get(),
      log.get(), log.get(), a.engine.get());
  Materialiser materialiser_b({.replica_id = "replica-b"}, log_b.get(),
                              log_b.get(), log_b.get(), b.engine.get());
  absl::StatusOr<StepResult> caught_up = materialiser_a->CatchUp(fleet);
  ASSERT_TRUE(caught_up.ok()) << caught_up.status();
  EXPECT_EQ(caught_up->position, uploads.size() + 1);
  ExpectSameState(StateOf(*a.engine, fleet), want);

  // One owner: B is refused while A renews.
  absl::StatusOr<StepResult> refused = materialiser_b.Step(fleet);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(refused.status().message(), ::testing::HasSubstr("replica-a"));

  // A stops renewing (it hangs); after the lease's 1 s, B takes the fleet
  // and rebuilds it from the log alone.
  const auto start = std::chrono::steady_clock::now();
  absl::StatusOr<StepResult> taken = materialiser_b.CatchUp(fleet);
  while (!taken.ok() &&
         std::chrono::steady_clock::now() - start < std::chrono::seconds(10)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    taken = materialiser_b.CatchUp(fleet);
  }
  ASSERT_TRUE(taken.ok()) << taken.status();
  EXPECT_GT(taken->revision, materialiser_a->lease(fleet)->revision);
  ExpectSameState(StateOf(*b.engine, fleet), want);

  // A wakes up: fenced, it applies nothing more and drops the fleet.
  ASSERT_TRUE(AppendUpload(*log, fleet, uploads[0], "late").ok());
  EXPECT_EQ(materialiser_a->Step(fleet).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_FALSE(materialiser_a->lease(fleet).has_value());
  ExpectSameState(StateOf(*a.engine, fleet), want);
}

// A restarted owner (same replica id, same store) takes its lease back at
// once and resumes after the position its store holds: the entries before
// it are not applied again.
TEST_F(MaterialiserTest, ARestartedOwnerResumesAfterItsStoredPosition) {
  const std::string fleet = "fleet-d";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  Replica embedded, a;
  for (size_t i = 0; i < 4; ++i) {
    ASSERT_TRUE(embedded.engine->Upload(fleet, uploads[i]).ok());
  }
  AppendUploads(*log, fleet, {uploads[0], uploads[1], uploads[2]});
  {
    Materialiser before({.replica_id = "replica-a"}, log.get(), log.get(),
                        log.get(), a.engine.get());
    absl::StatusOr<StepResult> done = before.CatchUp(fleet);
    ASSERT_TRUE(done.ok()) << done.status();
    EXPECT_EQ(done->applied, 3u);
  }
  // Restart: a new engine on the same store, the lease still held.
  a.engine.reset();
  absl::StatusOr<std::unique_ptr<engine::MemoryEngine>> reopened =
      engine::MemoryEngine::Open(
          testing_util::SmallOptions(), a.store.get(),
          [](size_t dimension) { return index::NewExactIndex(dimension); });
  ASSERT_TRUE(reopened.ok()) << reopened.status();
  a.engine = *std::move(reopened);
  EXPECT_EQ(*a.engine->LogPosition(fleet), 3u);
  AppendUploads(*log, fleet, {uploads[3]});
  Materialiser after({.replica_id = "replica-a"}, log.get(), log.get(),
                     log.get(), a.engine.get());
  absl::StatusOr<StepResult> resumed = after.CatchUp(fleet);
  ASSERT_TRUE(resumed.ok()) << resumed.status();
  EXPECT_EQ(resumed->applied, 1u);
  EXPECT_EQ(resumed->position, 4u);
  ExpectSameState(StateOf(*a.engine, fleet), StateOf(*embedded.engine, fleet));
}

// A new owner is not caught up until it applied the log as it stood when
// it took the fleet (its reads wait for that: ReplicatedMemory::Owner);
// entries appended after the take are ordinary lag. The cluster test's
// GetFleet right after a hand-over met the gap (NOT_FOUND for a fleet that
// existed, 1 run in CI's sanitizer build).
TEST_F(MaterialiserTest, ANewOwnerIsCaughtUpOnceItAppliedTheLogBeforeItsTake) {
  const std::string fleet = "fleet-take";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  AppendUploads(*log, fleet, {uploads[0], uploads[1], uploads[2]});
  Replica a;
  Materialiser owner({.replica_id = "replica-a", .batch = 1}, log.get(),
                     log.get(), log.get(), a.engine.get());
  EXPECT_FALSE(owner.Progress(fleet).has_value());
  absl::StatusOr<StepResult> first = owner.Step(fleet);
  ASSERT_TRUE(first.ok()) << first.status();
  std::optional<Materialiser::TakeProgress> progress = owner.Progress(fleet);
  ASSERT_TRUE(progress.has_value());
  EXPECT_EQ(progress->applied, 1u);
  EXPECT_EQ(progress->end_at_take, 3u);
  EXPECT_FALSE(progress->caught_up());
  ASSERT_TRUE(owner.Step(fleet).ok());
  EXPECT_FALSE(owner.Progress(fleet)->caught_up());
  ASSERT_TRUE(owner.Step(fleet).ok());
  EXPECT_TRUE(owner.Progress(fleet)->caught_up());
  AppendUploads(*log, fleet, {uploads[3]});
  progress = owner.Progress(fleet);
  EXPECT_EQ(progress->applied, 3u);
  EXPECT_TRUE(progress->caught_up());
  ASSERT_TRUE(owner.Release(fleet).ok());
  EXPECT_FALSE(owner.Progress(fleet).has_value());
}

// An owner that finds it was stopped for longer than the leases'
// time-to-live (its renewing thread did not run) takes the leases it
// could not renew meanwhile as lost, although NATS still holds them for it
// and would renew them: the fleet's watchers hear of it at once
// (OnLeaseLost), nothing more is applied under it, and the replica takes
// the fleet again only through Acquire.
TEST_F(MaterialiserTest, AnOwnerStoppedPastTheTtlTakesItsLeasesAsLost) {
  const std::string fleet = "fleet-p";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  AppendUploads(*log, fleet, {uploads[0]});
  Replica a;
  fleetmem::testing::ManualClock clock;
  Materialiser owner({.replica_id = "replica-a",
                      .renew_interval = absl::Milliseconds(300),
                      .lease_ttl = absl::Seconds(1),
                      .clock = &clock},
                     log.get(), log.get(), log.get(), a.engine.get());
  std::vector<std::string> lost;
  owner.OnLeaseLost([&](const std::string& id) { lost.push_back(id); });
  absl::StatusOr<StepResult> first = owner.Step(fleet);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->applied, 1u);

  // Renewed while due, on time: kept.
  clock.Advance(absl::Milliseconds(400));
  owner.RenewLeases();
  clock.Advance(absl::Milliseconds(400));
  owner.RenewLeases();
  EXPECT_TRUE(owner.Owns(fleet));
  EXPECT_TRUE(lost.empty());

  // The renewing thread did not run for 1.2 s (the replica was stopped):
  // lost here, though the lease is still this replica's in NATS.
  clock.Advance(absl::Milliseconds(1200));
  owner.RenewLeases();
  EXPECT_THAT(lost, ::testing::ElementsAre(fleet));
  absl::StatusOr<std::optional<Lease>> holder = log->Holder(fleet);
  ASSERT_TRUE(holder.ok()) << holder.status();
  ASSERT_TRUE(holder->has_value());
  EXPECT_EQ((*holder)->owner, "replica-a");
  AppendUploads(*log, fleet, {uploads[1]});
  absl::StatusOr<StepResult> fenced = owner.Step(fleet);
  EXPECT_EQ(fenced.status().code(), absl::StatusCode::kFailedPrecondition)
      << fenced.status();
  EXPECT_FALSE(owner.Owns(fleet));
  // The next step takes it again (its own lease, at once) and goes on.
  absl::StatusOr<StepResult> again = owner.Step(fleet);
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->position, 2u);
}

// An entry the memory refuses (another code dimension than the fleet's) is
// refused alike by every replica, and the log moves past it.
TEST_F(MaterialiserTest, AnEntryTheMemoryRefusesIsSkippedAlike) {
  const std::string fleet = "fleet-b";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  std::vector<core::MemoryTrace> wrong = uploads[1];
  for (core::MemoryTrace& trace : wrong) trace.code.resize(4);
  for (const auto& batch : {uploads[0], wrong, uploads[2]}) {
    ASSERT_TRUE(AppendUpload(*log, fleet, batch).ok());
  }
  Replica a;
  Materialiser materialiser({.replica_id = "replica-a"}, log.get(), log.get(),
                            log.get(), a.engine.get());
  absl::StatusOr<StepResult> done = materialiser.CatchUp(fleet);
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->position, 3u);
  const State state = StateOf(*a.engine, fleet);
  EXPECT_EQ(state.stats.traces + state.stats.pending_traces, 20u);
  ASSERT_TRUE(materialiser.Release(fleet).ok());
  EXPECT_FALSE(log->Holder(fleet)->has_value());
}

// RESOURCE_EXHAUSTED (a full disk: the store refuses writes) is not
// passed: the step stops at the entry and retries it; the entry applies
// once the store writes again. No limit refuses an entry (its upload was
// admitted before the log took it): a fleet's trace limit lowered below
// what its log holds applies the log whole.
TEST_F(MaterialiserTest, AnEntryRefusedForWantOfRoomIsNotPassed) {
  const std::string fleet = "fleet-e";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  AppendUploads(*log, fleet, {uploads[0]});
  auto memory = storage::NewInMemoryStore();
  engine::FlakyStore store(memory.get());
  engine::EngineOptions options = testing_util::SmallOptions();
  options.limits.max_traces_per_fleet = 15;
  absl::StatusOr<std::unique_ptr<engine::MemoryEngine>> engine =
      engine::MemoryEngine::Open(options, &store, [](size_t dimension) {
        return index::NewExactIndex(dimension);
      });
  ASSERT_TRUE(engine.ok()) << engine.status();
  Materialiser materialiser({.replica_id = "replica-a"}, log.get(), log.get(),
                            log.get(), engine->get());
  ASSERT_TRUE(materialiser.CatchUp(fleet).ok());
  AppendUploads(*log, fleet, {uploads[1], uploads[2]});
  store.fail_after = store.applies;
  store.failure = absl::ResourceExhaustedError("disk nearly full");
  for (int attempt = 0; attempt < 2; ++attempt) {
    absl::StatusOr<StepResult> step = materialiser.Step(fleet);
    EXPECT_EQ(step.status().code(), absl::StatusCode::kResourceExhausted);
  }
  EXPECT_EQ(*(*engine)->LogPosition(fleet), 1u);
  store.fail_after = -1;
  absl::StatusOr<StepResult> step = materialiser.CatchUp(fleet);
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->position, 3u);
  EXPECT_EQ((*engine)->HeldTraces(fleet), 30u);  // past the limit of 15
}

TEST_F(MaterialiserTest, IngestCutsEntriesPerRobotAndSizeAndRetriesAreFree) {
  const std::string fleet = "fleet-c";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  // One client message with two robots' traces, interleaved.
  std::vector<core::MemoryTrace> mixed;
  for (size_t i = 0; i < 10; ++i) {
    mixed.push_back(uploads[0][i]);
    mixed.push_back(uploads[1][i]);
  }
  absl::StatusOr<Ingested> whole = Ingest(*log, fleet, mixed, 1 << 20);
  ASSERT_TRUE(whole.ok()) << whole.status();
  EXPECT_EQ(whole->entries, 2u);
  EXPECT_EQ(whole->traces, 20u);
  absl::StatusOr<std::vector<engine::LogEntry>> entries =
      log->Read(fleet, 0, 10);
  ASSERT_TRUE(entries.ok());
  ASSERT_EQ(entries->size(), 2u);
  EXPECT_EQ((*entries)[0].id, "upload/2/r1/1-10");
  EXPECT_EQ((*entries)[1].id, "upload/2/r2/1-10");
  // The client's retry: the log holds both entries already.
  absl::StatusOr<Ingested> retry = Ingest(*log, fleet, mixed, 1 << 20);
  ASSERT_TRUE(retry.ok()) << retry.status();
  EXPECT_EQ(retry->duplicate_entries, 2u);
  EXPECT_EQ(log->Bounds(fleet)->last, 2u);

  // Entries of at most 400 bytes: r3's next 10 traces take several, each
  // within the bound.
  absl::StatusOr<Ingested> small = Ingest(*log, fleet, uploads[2], 400);
  ASSERT_TRUE(small.ok()) << small.status();
  EXPECT_GT(small->entries, 2u);
  EXPECT_EQ(small->traces, 10u);
  absl::StatusOr<std::vector<engine::LogEntry>> cut = log->Read(fleet, 2, 100);
  ASSERT_TRUE(cut.ok());
  ASSERT_EQ(cut->size(), small->entries);
  size_t traces = 0;
  for (const engine::LogEntry& entry : *cut) {
    EXPECT_FALSE(entry.traces().empty());
    traces += entry.traces().size();
  }
  EXPECT_EQ(traces, 10u);
  // A trace larger than an entry: refused, nothing appended.
  EXPECT_EQ(Ingest(*log, fleet, uploads[3], 50).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(log->Bounds(fleet)->last, 2 + small->entries);

  Replica embedded, a;
  for (const auto& batch : {uploads[0], uploads[1], uploads[2]}) {
    ASSERT_TRUE(embedded.engine->Upload(fleet, batch).ok());
  }
  Materialiser materialiser({.replica_id = "replica-a"}, log.get(), log.get(),
                            log.get(), a.engine.get());
  ASSERT_TRUE(materialiser.CatchUp(fleet).ok());
  ExpectSameState(StateOf(*a.engine, fleet), StateOf(*embedded.engine, fleet));
}

TEST(UploadIdTest, OneRobotPerEntryAndAStableId) {
  std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  absl::StatusOr<std::string> id = UploadId(uploads[0]);
  ASSERT_TRUE(id.ok());
  EXPECT_EQ(*id, "upload/2/r1/1-10");
  EXPECT_EQ(*UploadId(uploads[0]), *id);
  std::vector<core::MemoryTrace> mixed = uploads[0];
  mixed.push_back(uploads[1].front());
  EXPECT_EQ(UploadId(mixed).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(UploadId({}).status().code(), absl::StatusCode::kInvalidArgument);
}

// Consolidate and SampleReplay go through the log at the owner: the answer
// is what applying the entry did, a non-owner is refused, and a replica that
// rebuilds the fleet from the log draws the same samples and counts them
// once.
TEST_F(MaterialiserTest, CallsGoThroughTheLogAndEveryReplicaAppliesThemAlike) {
  const std::string fleet = "fleet-calls";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  AppendUploads(*log, fleet, uploads);
  Replica a, b, c;
  Materialiser owner({.replica_id = "replica-a"}, log.get(), log.get(),
                     log.get(), a.engine.get());
  Materialiser other({.replica_id = "replica-b"}, log.get(), log.get(),
                     log.get(), b.engine.get());
  EXPECT_EQ(owner.Consolidate(fleet).status().code(),
            absl::StatusCode::kUnavailable);  // not taken yet: retried
  // Pending traces for Consolidate: r1's 61..65 (a segment is 20).
  std::vector<core::MemoryTrace> pending(uploads[0].begin(),
                                         uploads[0].begin() + 5);
  for (size_t i = 0; i < pending.size(); ++i) pending[i].seq = 61 + i;
  AppendUploads(*log, fleet, {pending});
  ASSERT_TRUE(owner.CatchUp(fleet).ok());
  EXPECT_TRUE(owner.Owns(fleet));
  ASSERT_EQ(a.engine->GetStats(fleet)->pending_traces, 5u);

  absl::StatusOr<std::vector<core::MemoryTrace>> drawn =
      owner.SampleReplay(fleet, "r1", 5, "req-1");
  ASSERT_TRUE(drawn.ok()) << drawn.status();
  ASSERT_EQ(drawn->size(), 5u);
  // A retry of the same request: the same traces, counted once.
  absl::StatusOr<std::vector<core::MemoryTrace>> again =
      owner.SampleReplay(fleet, "r1", 5, "req-1");
  ASSERT_TRUE(again.ok()) << again.status();
  ASSERT_EQ(again->size(), drawn->size());
  for (size_t i = 0; i < drawn->size(); ++i) {
    EXPECT_EQ((*again)[i].key(), (*drawn)[i].key());
    EXPECT_EQ((*again)[i].replay_count, (*drawn)[i].replay_count);
  }
  ASSERT_TRUE(owner.SampleReplay(fleet, "r2", 7, "").ok());
  absl::StatusOr<engine::ConsolidateResult> consolidated =
      owner.Consolidate(fleet);
  ASSERT_TRUE(consolidated.ok()) << consolidated.status();
  EXPECT_GT(consolidated->consolidated_traces, 0u);
  EXPECT_EQ(a.engine->GetStats(fleet)->pending_traces, 0u);
  // The engine's refusal comes back; the entry is passed alike everywhere.
  EXPECT_EQ(owner.SampleReplay(fleet, "r1", 0, "").status().code(),
            absl::StatusCode::kInvalidArgument);
  const absl::Status not_owner =
      other.SampleReplay(fleet, "r1", 5, "").status();
  EXPECT_EQ(not_owner.code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(not_owner.message(),
              ::testing::HasSubstr("nothing of this call was logged"));
  // A sample's position is stored with the counts it changed (the retry
  // changed none; Consolidate applied again consolidates nothing).
  EXPECT_EQ(*a.engine->LogPosition(fleet), uploads.size() + 4);

  const State want = StateOf(*a.engine, fleet);
  ASSERT_TRUE(owner.Release(fleet).ok());
  Materialiser rebuilt({.replica_id = "replica-c"}, log.get(), log.get(),
                       log.get(), c.engine.get());
  absl::StatusOr<StepResult> done = rebuilt.CatchUp(fleet);
  ASSERT_TRUE(done.ok()) << done.status();
  EXPECT_EQ(done->position, uploads.size() + 6);
  ExpectSameState(StateOf(*c.engine, fleet), want);
}

// Snapshots: the owner stores one every `snapshot_every` entries and trims
// the log it covers; a replica with an empty store, and one whose store is
// behind the trimmed head, restore the latest and apply only the tail, and
// reach the owner's state exactly. The fleet's shape survives its first
// entry's trimming.
// A replica that takes a fleet whose log is trimmed and whose snapshot it
// cannot restore does not own the fleet, and says so at once: the watches
// it accepted while it held the lease end (OnLeaseLost), as for a lost
// lease. The next step takes the fleet again.
TEST_F(MaterialiserTest, ATakeWhoseRestoreFailsEndsTheFleetsWatches) {
  const std::string fleet = "fleet-bad-snap";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  AppendUploads(*log, fleet, Uploads());
  ASSERT_TRUE(
      log->Put(fleet, SnapshotInfo{6, 9, 8, "enc-v1"}, "not-image").ok());
  ASSERT_TRUE(log->Trim(fleet, 6).ok());
  Replica a;
  Materialiser taker({.replica_id = "replica-a"}, log.get(), log.get(),
                     log.get(), a.engine.get());
  std::vector<std::string> lost;
  taker.OnLeaseLost([&](const std::string& id) { lost.push_back(id); });
  absl::StatusOr<StepResult> step = taker.Step(fleet);
  EXPECT_EQ(step.status().code(), absl::StatusCode::kDataLoss) << step.status();
  EXPECT_FALSE(taker.Owns(fleet));
  EXPECT_EQ(lost, std::vector<std::string>{fleet});
  // Still its lease's holder: the next step takes it again, and fails alike.
  EXPECT_EQ(taker.Step(fleet).status().code(), absl::StatusCode::kDataLoss);
  EXPECT_EQ(lost.size(), 2u);
}

TEST_F(MaterialiserTest, SnapshotsLetNewOwnersSkipTheTrimmedLog) {
  const std::string fleet = "fleet-snap";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  const std::vector<std::vector<core::MemoryTrace>> head(uploads.begin(),
                                                         uploads.begin() + 9);
  const std::vector<std::vector<core::MemoryTrace>> tail(uploads.begin() + 9,
                                                         uploads.end());
  const MaterialiserOptions options{.replica_id = "replica-a",
                                    .batch = 5,
                                    .snapshot_every = 8,
                                    .restore_after = 1};
  Replica a, b, c;
  // B holds the first three uploads, applied before (its own position).
  for (uint64_t i = 0; i < 3; ++i) {
    ASSERT_TRUE(b.engine->Upload(fleet, uploads[i], i + 1).ok());
  }
  Materialiser owner(options, log.get(), log.get(), log.get(), a.engine.get());
  AppendUploads(*log, fleet, head);
  ASSERT_TRUE(owner.CatchUp(fleet).ok());
  owner.WaitForSnapshots();
  absl::StatusOr<std::optional<SnapshotInfo>> first = log->Latest(fleet);
  ASSERT_TRUE(first.ok() && first->has_value()) << first.status();
  EXPECT_EQ((*first)->sequence, 9u);  // the step that passed 8
  EXPECT_EQ((*first)->code_dimension, 8u);
  EXPECT_EQ(log->Bounds(fleet)->first, 10u);  // trimmed through it
  // An older snapshot never replaces a newer one.
  EXPECT_EQ(log->Put(fleet, SnapshotInfo{5, 1, 8, "enc-v1"}, "x").code(),
            absl::StatusCode::kFailedPrecondition);

  AppendUploads(*log, fleet, tail);
  ASSERT_TRUE(owner.CatchUp(fleet).ok());
  ASSERT_TRUE(owner.SampleReplay(fleet, "r2", 6, "req-9").ok());
  ASSERT_TRUE(owner.Consolidate(fleet).ok());
  owner.WaitForSnapshots();
  const State want = StateOf(*a.engine, fleet);
  ASSERT_GT(want.stats.clusters_forgotten, 0u);
  absl::StatusOr<std::optional<SnapshotInfo>> latest = log->Latest(fleet);
  ASSERT_TRUE(latest.ok() && latest->has_value());
  // 9 + 8 = 17 passed at 18; the sample (19) and Consolidate (20) follow.
  EXPECT_EQ((*latest)->sequence, 18u);
  EXPECT_EQ(log->Bounds(fleet)->first, (*latest)->sequence + 1);

  absl::StatusOr<std::optional<engine::FleetShape>> shape =
      FleetShapeFromLog(*log, log.get(), fleet);
  ASSERT_TRUE(shape.ok() && shape->has_value()) << shape.status();
  EXPECT_EQ((*shape)->code_dimension, 8u);
  EXPECT_EQ((*shape)->encoder_version, "enc-v1");

  ASSERT_TRUE(owner.Release(fleet).ok());
  for (Replica* replica : {&b, &c}) {
    Materialiser taker({.replica_id = "replica-t", .restore_after = 1},
                       log.get(), log.get(), log.get(), replica->engine.get());
    absl::StatusOr<StepResult> step = taker.Step(fleet);
    ASSERT_TRUE(step.ok()) << step.status();
    EXPECT_EQ(step->restored, (*latest)->sequence);
    ASSERT_TRUE(taker.CatchUp(fleet).ok());
    ExpectSameState(StateOf(*replica->engine, fleet), want);
    EXPECT_EQ(*replica->engine->LogPosition(fleet),
              *a.engine->LogPosition(fleet));
    ASSERT_TRUE(taker.Release(fleet).ok());
  }
}

// Issue 46: a deleted fleet's data leaves JetStream at once. The owner
// snapshots the deleted fleet as soon as it applied the DeleteFleet (the
// snapshot replaces the fleet's earlier one; the log is trimmed through
// it); a replica that takes the fleet over restores it as deleted; the
// fleet made anew after it, with another shape, is read from the log.
TEST_F(MaterialiserTest, ADeletedFleetLeavesTheLogAndItsSnapshotAtOnce) {
  const std::string fleet = "fleet-deleted";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  const MaterialiserOptions options{
      .replica_id = "replica-a", .snapshot_every = 12, .restore_after = 1};
  Replica a, b;
  Materialiser owner(options, log.get(), log.get(), log.get(), a.engine.get());
  AppendUploads(*log, fleet, uploads);  // 18 entries
  ASSERT_TRUE(owner.CatchUp(fleet).ok());
  owner.WaitForSnapshots();
  absl::StatusOr<std::optional<SnapshotInfo>> before = log->Latest(fleet);
  ASSERT_TRUE(before.ok() && before->has_value()) << before.status();
  EXPECT_EQ((*before)->code_dimension, 8u);  // the full fleet's image
  ASSERT_GT(a.engine->GetStats(fleet)->traces, 0u);

  absl::StatusOr<engine::AppliedRecord> deleted =
      owner.Call(fleet, engine::DeleteFleetRecord{});
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  owner.WaitForSnapshots();
  absl::StatusOr<std::optional<SnapshotInfo>> after = log->Latest(fleet);
  ASSERT_TRUE(after.ok() && after->has_value()) << after.status();
  EXPECT_EQ((*after)->sequence, 19u);  // the delete's entry
  EXPECT_EQ((*after)->code_dimension, 0u);
  absl::StatusOr<engine::LogBounds> bounds = log->Bounds(fleet);
  ASSERT_TRUE(bounds.ok());
  EXPECT_EQ(bounds->first, 20u);  // every entry of the deleted fleet purged
  EXPECT_EQ(bounds->last, 19u);
  absl::StatusOr<std::optional<engine::FleetShape>> shape =
      FleetShapeFromLog(*log, log.get(), fleet);
  ASSERT_TRUE(shape.ok()) << shape.status();
  EXPECT_FALSE(shape->has_value());

  // Made anew with 4-d codes: the shape is the new upload's.
  std::vector<core::MemoryTrace> remade(uploads[0].begin(),
                                        uploads[0].begin() + 5);
  for (core::MemoryTrace& t : remade) t.code.resize(4);
  AppendUploads(*log, fleet, {remade});
  shape = FleetShapeFromLog(*log, log.get(), fleet);
  ASSERT_TRUE(shape.ok() && shape->has_value()) << shape.status();
  EXPECT_EQ((*shape)->code_dimension, 4u);
  ASSERT_TRUE(owner.CatchUp(fleet).ok());
  ASSERT_TRUE(owner.Release(fleet).ok());

  // B had applied nothing: it restores the deleted fleet's snapshot, then
  // the new upload after it, and holds what A holds.
  Materialiser taker({.replica_id = "replica-b", .restore_after = 1}, log.get(),
                     log.get(), log.get(), b.engine.get());
  absl::StatusOr<StepResult> step = taker.Step(fleet);
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->restored, 19u);
  ASSERT_TRUE(taker.CatchUp(fleet).ok());
  ExpectSameState(StateOf(*b.engine, fleet), StateOf(*a.engine, fleet));
  EXPECT_EQ(b.engine->GetStats(fleet)->traces +
                b.engine->GetStats(fleet)->pending_traces,
            5u);
  EXPECT_EQ(*b.engine->LogPosition(fleet), 20u);
  ASSERT_TRUE(taker.Release(fleet).ok());
}

// A previous owner's snapshot writer may trim the log after another replica
// took the fleet and began applying it: that replica's next read finds its
// entries gone and restores the snapshot instead of passing them.
TEST_F(MaterialiserTest, ALogTrimmedUnderANewOwnerIsRestoredNotSkipped) {
  const std::string fleet = "fleet-late";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  const std::vector<std::vector<core::MemoryTrace>> first(uploads.begin(),
                                                          uploads.begin() + 6);
  AppendUploads(*log, fleet, first);
  Replica a, d;
  Materialiser old_owner({.replica_id = "replica-a", .snapshot_every = 0},
                         log.get(), log.get(), log.get(), a.engine.get());
  ASSERT_TRUE(old_owner.CatchUp(fleet).ok());
  const State want = StateOf(*a.engine, fleet);
  ASSERT_TRUE(old_owner.Release(fleet).ok());

  Materialiser taker({.replica_id = "replica-d",
                      .batch = 2,
                      .snapshot_every = 0,
                      .restore_after = 1000},
                     log.get(), log.get(), log.get(), d.engine.get());
  absl::StatusOr<StepResult> step = taker.Step(fleet);
  ASSERT_TRUE(step.ok()) << step.status();
  ASSERT_EQ(step->position, 2u);
  // The old owner's late snapshot through 6, and its trim.
  absl::StatusOr<engine::FleetImage> image = a.engine->ExportFleet(fleet, 6);
  ASSERT_TRUE(image.ok()) << image.status();
  absl::StatusOr<std::string> bytes = storage::EncodeFleetImage(*image);
  ASSERT_TRUE(bytes.ok());
  ASSERT_TRUE(
      log->Put(fleet, SnapshotInfo{6, bytes->size(), 8, "enc-v1"}, *bytes)
          .ok());
  ASSERT_TRUE(log->Trim(fleet, 6).ok());
  EXPECT_EQ(log->Read(fleet, 2, 1).status().code(),
            absl::StatusCode::kOutOfRange);

  step = taker.Step(fleet);
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->restored, 6u);
  EXPECT_EQ(step->position, 6u);
  ExpectSameState(StateOf(*d.engine, fleet), want);
}

// An upload that creates a fleet is appended only as its log's first
// entry: a second upload that also believed it creates the fleet is
// refused with nothing appended (the receiving replica then checks it
// against the first one's shape).
TEST_F(MaterialiserTest, OnlyOneUploadCreatesAFleet) {
  const std::string fleet = "fleet-new";
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::vector<std::vector<core::MemoryTrace>> uploads = Uploads();
  absl::StatusOr<Ingested> first =
      Ingest(*log, fleet, uploads[0], 1 << 20, /*creates_fleet=*/true);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_EQ(first->last_sequence, 1u);
  absl::StatusOr<Ingested> second =
      Ingest(*log, fleet, uploads[1], 1 << 20, /*creates_fleet=*/true);
  EXPECT_EQ(second.status().code(), absl::StatusCode::kFailedPrecondition)
      << second.status();
  EXPECT_EQ(log->Bounds(fleet)->last, 1u);
  // As an ordinary upload it is appended.
  second = Ingest(*log, fleet, uploads[1], 1 << 20);
  ASSERT_TRUE(second.ok()) << second.status();
  EXPECT_EQ(log->Bounds(fleet)->last, 2u);
}

}  // namespace
}  // namespace fleetmem::cluster
