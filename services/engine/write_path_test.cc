#include "services/engine/write_path.h"

#include <atomic>
#include <memory>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/engine/memory_engine.h"
#include "services/engine/testing/forwarding_store.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_log.h"
#include "services/storage/in_memory_store.h"

namespace fleetmem::engine {
namespace {

using ::testing::HasSubstr;

constexpr size_t kDimension = 4;
constexpr absl::Duration kWait = absl::Seconds(20);

EngineOptions SmallOptions() {
  EngineOptions options;
  options.memory.clusters_per_batch = 2;
  options.segment_size = 10;
  return options;
}

std::vector<core::MemoryTrace> Traces(const std::string& robot_id,
                                      uint64_t first_seq, size_t count) {
  std::mt19937_64 rng(first_seq);
  std::normal_distribution<float> normal;
  std::vector<core::MemoryTrace> traces;
  for (size_t i = 0; i < count; ++i) {
    core::MemoryTrace trace;
    trace.robot_id = robot_id;
    trace.seq = first_seq + i;
    trace.code.resize(kDimension);
    for (float& value : trace.code) value = normal(rng);
    trace.place = core::Place{static_cast<double>(trace.seq), 0, 0, 0};
    trace.reward = 1.0f;
    trace.encoder_version = "v1";
    traces.push_back(std::move(trace));
  }
  return traces;
}

// A store and its log: the store's applies (the appliers' writes) wait
// while the gate is closed, and the log's appends can be made to fail or
// counted.
class GatedStorage : public ForwardingStore, public ForwardingLog {
 public:
  GatedStorage(MemoryStore* store, FleetLog* log)
      : ForwardingStore(store), ForwardingLog(log) {}

  absl::Status Apply(std::string_view fleet_id,
                     const FleetMutation& mutation) override {
    {
      absl::MutexLock lock(&mu_);
      while (!applies_open_) changed_.Wait(&mu_);
      if (!apply_error_.ok()) return apply_error_;
    }
    return ForwardingStore::Apply(fleet_id, mutation);
  }
  absl::StatusOr<std::vector<AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const LogAppend> entries,
      const AppendOptions& options) override {
    {
      absl::MutexLock lock(&mu_);
      ++appends_;
      appended_entries_.push_back(entries.size());
      if (!append_error_.ok()) return append_error_;
      while (!appends_open_) changed_.Wait(&mu_);
    }
    return ForwardingLog::Append(fleet_id, entries, options);
  }

  void SetApplies(bool open) {
    absl::MutexLock lock(&mu_);
    applies_open_ = open;
    changed_.SignalAll();
  }
  void SetAppends(bool open) {
    absl::MutexLock lock(&mu_);
    appends_open_ = open;
    changed_.SignalAll();
  }
  void FailAppends(absl::Status error) {
    absl::MutexLock lock(&mu_);
    append_error_ = std::move(error);
  }
  void FailApplies(absl::Status error) {
    absl::MutexLock lock(&mu_);
    apply_error_ = std::move(error);
  }
  int appends() {
    absl::MutexLock lock(&mu_);
    return appends_;
  }
  std::vector<size_t> appended_entries() {
    absl::MutexLock lock(&mu_);
    return appended_entries_;
  }

 private:
  absl::Mutex mu_;
  // A CondVar, not Mutex::Await: `make test-tsan` annotates CondVar waits
  // (tools/tsan/absl_mutex_annotations.cc), not Await.
  absl::CondVar changed_;
  bool applies_open_ ABSL_GUARDED_BY(mu_) = true;
  bool appends_open_ ABSL_GUARDED_BY(mu_) = true;
  absl::Status append_error_ ABSL_GUARDED_BY(mu_);
  absl::Status apply_error_ ABSL_GUARDED_BY(mu_);
  int appends_ ABSL_GUARDED_BY(mu_) = 0;
  std::vector<size_t> appended_entries_ ABSL_GUARDED_BY(mu_);
};

class WritePathTest : public ::testing::Test {
 protected:
  void Open(WritePathOptions options = {}) {
    path_.reset();
    engine_.reset();
    absl::StatusOr<std::unique_ptr<MemoryEngine>> engine = MemoryEngine::Open(
        engine_options_, &store_,
        [](size_t dimension) { return index::NewExactIndex(dimension); });
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = *std::move(engine);
    absl::StatusOr<std::unique_ptr<WritePath>> path =
        WritePath::Open(options, engine_.get(), &store_);
    ASSERT_TRUE(path.ok()) << path.status();
    path_ = *std::move(path);
  }
  void TearDown() override {
    store_.SetApplies(true);
    store_.SetAppends(true);
  }
  uint64_t Held(const std::string& fleet) {
    absl::StatusOr<FleetStats> stats = engine_->GetStats(fleet);
    return stats.ok() ? stats->traces + stats->pending_traces : 0;
  }

  EngineOptions engine_options_ = SmallOptions();
  std::unique_ptr<MemoryStore> memory_ = storage::NewInMemoryStore();
  std::unique_ptr<FleetLog> log_ = storage::NewInMemoryLog();
  GatedStorage store_{memory_.get(), log_.get()};
  std::unique_ptr<MemoryEngine> engine_;
  std::unique_ptr<WritePath> path_;
};

TEST_F(WritePathTest, AcknowledgesAtTheAppendAndAppliesBehindIt) {
  Open();
  store_.SetApplies(false);  // the applier cannot store anything yet
  const std::vector<core::MemoryTrace> traces = Traces("r1", 1, 12);
  absl::StatusOr<Appended> appended = path_->Append("f", traces, true);
  ASSERT_TRUE(appended.ok()) << appended.status();
  EXPECT_EQ(appended->accepted, 12u);
  EXPECT_EQ(appended->sequence, 1u);
  Backlog backlog = path_->GetBacklog("f");
  EXPECT_EQ(backlog.entries, 1u);
  EXPECT_EQ(backlog.traces, 12u);
  EXPECT_EQ(backlog.appended_through, 1u);
  EXPECT_EQ(backlog.applied_through, 0u);
  EXPECT_EQ(
      path_->WaitApplied("f", 1, absl::Now() + absl::Milliseconds(50)).code(),
      absl::StatusCode::kDeadlineExceeded);

  store_.SetApplies(true);
  ASSERT_TRUE(path_->WaitApplied("f", 1, absl::Now() + kWait).ok());
  EXPECT_EQ(appended->applied->consolidations, 1u);  // segment_size 10
  EXPECT_EQ(Held("f"), 12u);
  backlog = path_->GetBacklog("f");
  EXPECT_EQ(backlog.traces, 0u);
  EXPECT_EQ(backlog.applied_through, 1u);
  EXPECT_EQ(*engine_->LogPosition("f"), 1u);
  // Applied entries leave the log (trimmed after their turn).
  const absl::Time give_up = absl::Now() + kWait;
  while (!store_.Read("f", 0, 10)->empty() && absl::Now() < give_up) {
    absl::SleepFor(absl::Milliseconds(1));
  }
  EXPECT_TRUE(store_.Read("f", 0, 10)->empty());
}

TEST_F(WritePathTest, DuplicatesAreCountedAtTheAppendAgainstTheBacklogToo) {
  std::atomic<uint64_t> observed{0};
  WritePathOptions options;
  options.on_duplicates = [&observed](std::string_view fleet,
                                      uint64_t duplicates) {
    EXPECT_EQ(fleet, "f");
    observed += duplicates;
  };
  Open(options);
  store_.SetApplies(false);
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 5)).ok());
  // Not applied yet: the engine has not seen seqs 1..5, the log has.
  std::vector<core::MemoryTrace> again = Traces("r1", 4, 4);  // 4..7
  again.push_back(again.back());                              // 7 twice
  absl::StatusOr<Appended> appended = path_->Append("f", again);
  ASSERT_TRUE(appended.ok()) << appended.status();
  EXPECT_EQ(appended->accepted, 2u);    // 6, 7
  EXPECT_EQ(appended->duplicates, 3u);  // 4, 5, and 7 again
  absl::StatusOr<Appended> none = path_->Append("f", Traces("r1", 1, 2));
  ASSERT_TRUE(none.ok());
  EXPECT_EQ(none->sequence, 0u);  // nothing appended
  store_.SetApplies(true);
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 7u);
  EXPECT_EQ(observed.load(), 5u);  // 3, then 2 (the metrics' duplicates)
}

TEST_F(WritePathTest, InvalidUploadsChangeNothingAndMakeNoFleet) {
  Open();
  std::vector<core::MemoryTrace> bad = Traces("r1", 1, 3);
  bad[2].code.push_back(1.0f);  // another dimension
  EXPECT_EQ(path_->Append("f", bad).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(path_->GetBacklog("f").appended_through, 0u);
  EXPECT_TRUE(store_.Fleets()->empty());
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 3)).ok());
  // The fleet's shape is fixed by its first upload, before it is applied.
  std::vector<core::MemoryTrace> wider = Traces("r2", 1, 1);
  wider[0].code.push_back(1.0f);
  absl::StatusOr<Appended> refused = path_->Append("f", wider);
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(refused.status().message(), HasSubstr("dimension"));
}

TEST_F(WritePathTest, FleetsPastMaxFleetsLeaveNothingBehind) {
  EngineOptions options = SmallOptions();
  options.limits.max_fleets = 1;
  absl::StatusOr<std::unique_ptr<MemoryEngine>> engine = MemoryEngine::Open(
      options, &store_,
      [](size_t dimension) { return index::NewExactIndex(dimension); });
  ASSERT_TRUE(engine.ok());
  engine_ = *std::move(engine);
  absl::StatusOr<std::unique_ptr<WritePath>> path =
      WritePath::Open({}, engine_.get(), &store_);
  ASSERT_TRUE(path.ok());
  path_ = *std::move(path);
  ASSERT_TRUE(path_->Append("first", Traces("r1", 1, 2)).ok());
  for (int i = 0; i < 3; ++i) {
    absl::StatusOr<Appended> refused =
        path_->Append("extra-" + std::to_string(i), Traces("r1", 1, 2));
    EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
    EXPECT_THAT(refused.status().message(), HasSubstr("max_fleets"));
  }
  EXPECT_EQ(path_->Backlogs().size(), 1u);  // no log kept for them
}

TEST_F(WritePathTest, AFullBacklogRefusesWithItsSizeAndAgeAndRecovers) {
  WritePathOptions options;
  options.max_backlog_traces = 20;
  Open(options);
  store_.SetApplies(false);
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 15)).ok());
  absl::StatusOr<Appended> refused = path_->Append("f", Traces("r1", 16, 10));
  ASSERT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.status().message(), HasSubstr("backlog holds 15 traces"));
  EXPECT_THAT(refused.status().message(), HasSubstr("max_backlog_traces"));
  // Refused: its seqs are not taken (a retry is not a duplicate).
  store_.SetApplies(true);
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  absl::StatusOr<Appended> retried = path_->Append("f", Traces("r1", 16, 10));
  ASSERT_TRUE(retried.ok()) << retried.status();
  EXPECT_EQ(retried->accepted, 10u);
}

// A caller waiting for its entry to be applied hears at once when the store
// refuses the apply (a full disk), not at its deadline; the entry stays
// durable and is applied once writes resume.
TEST_F(WritePathTest, AWaiterHearsOfAnApplyTheStoreRefuses) {
  WritePathOptions options;
  options.retry_interval = absl::Milliseconds(20);
  Open(options);
  store_.FailApplies(absl::ResourceExhaustedError("disk nearly full"));
  absl::StatusOr<Appended> appended = path_->Append("f", Traces("r1", 1, 4));
  ASSERT_TRUE(appended.ok()) << appended.status();
  const absl::Status waited = path_->WaitApplied(
      "f", appended->sequence, absl::Now() + absl::Seconds(60));
  EXPECT_EQ(waited.code(), absl::StatusCode::kResourceExhausted) << waited;
  EXPECT_THAT(waited.message(), HasSubstr("is durable"));
  EXPECT_THAT(waited.message(), HasSubstr("disk nearly full"));
  store_.FailApplies(absl::OkStatus());
  ASSERT_TRUE(
      path_->WaitApplied("f", appended->sequence, absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 4u);
}

TEST_F(WritePathTest, AFailedAppendStoresNothingAndTakesNoSeq) {
  Open();
  store_.FailAppends(absl::ResourceExhaustedError("disk nearly full"));
  EXPECT_EQ(path_->Append("f", Traces("r1", 1, 4)).status().code(),
            absl::StatusCode::kResourceExhausted);
  store_.FailAppends(absl::OkStatus());
  absl::StatusOr<Appended> retried = path_->Append("f", Traces("r1", 1, 4));
  ASSERT_TRUE(retried.ok()) << retried.status();
  EXPECT_EQ(retried->accepted, 4u);
  EXPECT_EQ(retried->sequence, 1u);
}

TEST_F(WritePathTest, ConcurrentUploadsShareOneStoreWrite) {
  Open();
  store_.SetAppends(false);  // the first write waits: the rest queue
  std::vector<std::thread> uploads;
  std::vector<absl::StatusOr<Appended>> results(5, Appended{});
  uploads.emplace_back(
      [&] { results[0] = path_->Append("f", Traces("r0", 1, 3)); });
  while (store_.appends() < 1) absl::SleepFor(absl::Milliseconds(1));
  for (int i = 1; i < 5; ++i) {
    uploads.emplace_back([&, i] {
      results[i] = path_->Append("f", Traces("r" + std::to_string(i), 1, 3));
    });
  }
  // The followers queue behind the leader's write.
  while (path_->QueuedUploads("f") < 4) absl::SleepFor(absl::Milliseconds(1));
  store_.SetAppends(true);
  for (std::thread& upload : uploads) upload.join();
  for (const auto& result : results)
    ASSERT_TRUE(result.ok()) << result.status();
  // Two writes: the first upload's, then the four that queued behind it.
  EXPECT_THAT(store_.appended_entries(), ::testing::ElementsAre(1u, 4u));
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 15u);
}

// One caller's uploads (a stream's messages) go into one store write, each
// its own entry with its own result, in order; empty ones and a refused one
// change nothing of the others, also for a fleet they make.
TEST_F(WritePathTest, ManyUploadsOfOneCallerShareOneStoreWrite) {
  Open();
  const std::vector<core::MemoryTrace> a = Traces("r1", 1, 3);
  const std::vector<core::MemoryTrace> b = Traces("r1", 4, 2);
  std::vector<core::MemoryTrace> bad = Traces("r2", 1, 1);
  bad[0].code.push_back(1.0f);  // another dimension
  const std::vector<core::MemoryTrace> c = Traces("r2", 1, 4);
  const std::span<const core::MemoryTrace> uploads[] = {{}, a, {}, b, bad, c};
  std::vector<absl::StatusOr<Appended>> results =
      path_->AppendMany("f", uploads);
  ASSERT_EQ(results.size(), 6u);
  EXPECT_TRUE(results[0].ok() && results[0]->sequence == 0);
  ASSERT_TRUE(results[1].ok()) << results[1].status();
  EXPECT_EQ(results[1]->sequence, 1u);  // made the fleet, alone
  EXPECT_TRUE(results[2].ok() && results[2]->sequence == 0);
  ASSERT_TRUE(results[3].ok()) << results[3].status();
  EXPECT_EQ(results[3]->sequence, 2u);
  EXPECT_EQ(results[4].status().code(), absl::StatusCode::kInvalidArgument);
  ASSERT_TRUE(results[5].ok()) << results[5].status();
  EXPECT_EQ(results[5]->sequence, 3u);
  EXPECT_EQ(results[5]->accepted, 4u);
  // The first write made the fleet; the rest went in one.
  EXPECT_THAT(store_.appended_entries(), ::testing::ElementsAre(1u, 2u));
  // Only empty uploads, or none, to a fleet that does not exist: nothing.
  const std::span<const core::MemoryTrace> empty[] = {{}, {}};
  results = path_->AppendMany("g", empty);
  ASSERT_EQ(results.size(), 2u);
  EXPECT_TRUE(results[0].ok() && results[1].ok());
  EXPECT_TRUE(path_->AppendMany("g", {}).empty());
  EXPECT_EQ(path_->GetBacklog("g").appended_through, 0u);
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 9u);
}

TEST_F(WritePathTest, OpenAppliesTheAcknowledgedTailOnceAfterACrash) {
  // What a crashed server leaves: the log holds entries 1..3, of which the
  // engine had applied 1 (stored with its position) but not trimmed it.
  Open();
  path_.reset();
  const std::vector<core::MemoryTrace> first = Traces("r1", 1, 4);
  const std::vector<core::MemoryTrace> second = Traces("r1", 5, 4);
  const std::vector<core::MemoryTrace> third = Traces("r2", 1, 3);
  const LogAppend entries[] = {
      {UploadRecord{first}}, {UploadRecord{second}}, {UploadRecord{third}}};
  absl::StatusOr<std::vector<AppendedEntry>> logged =
      log_->Append("f", entries, {});
  ASSERT_TRUE(logged.ok()) << logged.status();
  ASSERT_EQ(logged->back().sequence, 3u);
  // The applier applied entry 1 (stored with its position), then crashed.
  ASSERT_TRUE(engine_->Upload("f", first, 1).ok());

  Open();
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 11u);  // 1..4 once, 5..8, r2's 1..3
  EXPECT_EQ(*engine_->LogPosition("f"), 3u);
  // The recovered tail's seqs are duplicates for new uploads, and new
  // entries follow the recovered ones.
  absl::StatusOr<Appended> again = path_->Append("f", Traces("r2", 1, 4));
  ASSERT_TRUE(again.ok());
  EXPECT_EQ(again->accepted, 1u);
  EXPECT_EQ(again->sequence, 4u);
}

// The limits admit an upload before it is acknowledged (admission.h);
// applying it meets none of them. An entry acknowledged under a limit that
// was lowered before it was applied (a restart with a new config) is
// applied, and the log goes on; before issue 45 the entry was refused at
// every retry and the fleet's log stood still behind it.
TEST_F(WritePathTest, AnAcknowledgedEntryAppliesPastALimitLoweredSince) {
  engine_options_.limits.max_traces_per_fleet = 100;
  Open();
  // The store refuses the apply (it does not hold the applier: a closed
  // gate would, and the stop below would wait for it forever).
  store_.FailApplies(absl::UnavailableError("store busy"));
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 30)).ok());
  path_.reset();  // the server stops before the entry is applied
  store_.FailApplies(absl::OkStatus());
  engine_options_.limits.max_traces_per_fleet = 10;
  engine_options_.limits.max_code_dimension = 2;  // the fleet's codes: 4
  Open();
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 30u);
  EXPECT_TRUE(path_->GetBacklog("f").apply_error.ok());
  // New uploads meet the lowered limit before they are acknowledged.
  absl::StatusOr<Appended> refused = path_->Append("f", Traces("r1", 31, 1));
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.status().message(), HasSubstr("max_traces_per_fleet"));
}

TEST_F(WritePathTest, AFleetOnlyInItsLogIsMadeWhenApplied) {
  // The first upload of a fleet, acknowledged, then the server crashed.
  const std::vector<core::MemoryTrace> traces = Traces("r1", 1, 3);
  const LogAppend entries[] = {{UploadRecord{traces}}};
  ASSERT_TRUE(log_->Append("new", entries, {}).ok());
  store_.SetApplies(false);
  Open();
  // Its shape is known before it is applied.
  std::vector<core::MemoryTrace> wider = Traces("r2", 1, 1);
  wider[0].code.push_back(0.5f);
  EXPECT_EQ(path_->Append("new", wider).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(path_->GetBacklog("new").traces, 3u);
  store_.SetApplies(true);
  ASSERT_TRUE(path_->WaitAppliedAll("new", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("new"), 3u);
}

TEST_F(WritePathTest, StopAnswersWaitersAndRefusesUploads) {
  Open();
  store_.SetApplies(false);
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 2)).ok());
  absl::Status waited;
  std::thread waiter(
      [&] { waited = path_->WaitApplied("f", 1, absl::InfiniteFuture()); });
  absl::SleepFor(absl::Milliseconds(50));
  std::thread stopper([&] { path_->Stop(); });
  absl::SleepFor(absl::Milliseconds(50));
  store_.SetApplies(true);  // the applier finishes its entry and ends
  stopper.join();
  waiter.join();
  // Either applied before the stop, or told it will be at the next start.
  EXPECT_TRUE(waited.ok() || absl::IsUnavailable(waited)) << waited;
  EXPECT_EQ(path_->Append("f", Traces("r1", 3, 1)).status().code(),
            absl::StatusCode::kUnavailable);
}

// Consolidate and SampleReplay are log entries in embedded mode too
// (EmbeddedMemory::Call), ordered after the uploads acknowledged before
// them, answered with what applying them did.
TEST_F(WritePathTest, ACallIsLoggedAfterTheUploadsBeforeItAndAnswersWhatItDid) {
  Open();
  store_.SetApplies(false);  // the call queues behind the upload
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 6)).ok());
  absl::StatusOr<Appended> consolidate =
      path_->AppendCall("f", ConsolidateRecord{});
  ASSERT_TRUE(consolidate.ok()) << consolidate.status();
  EXPECT_EQ(consolidate->sequence, 2u);
  EXPECT_EQ(consolidate->accepted, 0u);
  EXPECT_EQ(path_->GetBacklog("f").entries, 2u);
  store_.SetApplies(true);
  ASSERT_TRUE(path_->WaitApplied("f", 2, absl::Now() + kWait).ok());
  ASSERT_NE(consolidate->applied, nullptr);
  EXPECT_TRUE(consolidate->applied->refused.ok());
  // The upload's 6 pending traces (below segment_size 10) consolidated.
  EXPECT_EQ(consolidate->applied->consolidated.consolidated_traces, 6u);

  absl::StatusOr<Appended> sample =
      path_->AppendCall("f", SampleReplayRecord{"r1", 3, "refresh-1"});
  ASSERT_TRUE(sample.ok()) << sample.status();
  ASSERT_TRUE(
      path_->WaitApplied("f", sample->sequence, absl::Now() + kWait).ok());
  ASSERT_EQ(sample->applied->sample.size(), 3u);
  // Drawn under the entry's sequence: the draw a replica applying the same
  // entry makes (the direct call with that position).
  absl::StatusOr<Appended> again =
      path_->AppendCall("f", SampleReplayRecord{"r1", 3, "refresh-1"});
  ASSERT_TRUE(again.ok());
  ASSERT_TRUE(
      path_->WaitApplied("f", again->sequence, absl::Now() + kWait).ok());
  ASSERT_EQ(again->applied->sample.size(), 3u);
  for (size_t i = 0; i < 3; ++i) {  // a retry: the same traces
    EXPECT_EQ(again->applied->sample[i].key(),
              sample->applied->sample[i].key());
  }

  // A fleet written into the engine directly (a restored image), never
  // through this write path: its log is made as a restart makes it.
  ASSERT_TRUE(engine_->Upload("direct", Traces("r9", 1, 2)).ok());
  absl::StatusOr<Appended> adopted =
      path_->AppendCall("direct", ConsolidateRecord{});
  ASSERT_TRUE(adopted.ok()) << adopted.status();
  ASSERT_TRUE(
      path_->WaitApplied("direct", adopted->sequence, absl::Now() + kWait)
          .ok());
  EXPECT_EQ(adopted->applied->consolidated.consolidated_traces, 2u);

  // A fleet with no upload acknowledged: NOT_FOUND, nothing logged.
  EXPECT_EQ(path_->AppendCall("g", ConsolidateRecord{}).status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(log_->Bounds("g")->last, 0u);
  EXPECT_EQ(path_->AppendCall("f", UploadRecord{}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

// A call's entry applied and trimmed leaves the engine's position where it
// was (it stores no traces): after a restart the write path knows it was
// applied, so the next call does not wait for it.
TEST_F(WritePathTest, AfterARestartATrimmedCallEntryIsNotWaitedFor) {
  Open();
  ASSERT_TRUE(path_->Append("f", Traces("r1", 1, 4)).ok());
  absl::StatusOr<Appended> call = path_->AppendCall("f", ConsolidateRecord{});
  ASSERT_TRUE(call.ok()) << call.status();
  ASSERT_TRUE(
      path_->WaitApplied("f", call->sequence, absl::Now() + kWait).ok());
  const absl::Time give_up = absl::Now() + kWait;
  while (!store_.Read("f", 0, 10)->empty() && absl::Now() < give_up) {
    absl::SleepFor(absl::Milliseconds(1));
  }
  ASSERT_TRUE(store_.Read("f", 0, 10)->empty());
  EXPECT_EQ(*engine_->LogPosition("f"), 1u);  // the upload's

  Open();  // a restart
  const Backlog backlog = path_->GetBacklog("f");
  EXPECT_EQ(backlog.appended_through, call->sequence);
  EXPECT_EQ(backlog.applied_through, call->sequence);
  EXPECT_TRUE(path_->WaitAppliedAll("f", absl::Now()).ok());
  absl::StatusOr<Appended> next = path_->AppendCall("f", ConsolidateRecord{});
  ASSERT_TRUE(next.ok());
  EXPECT_EQ(next->sequence, call->sequence + 1);
  EXPECT_TRUE(
      path_->WaitApplied("f", next->sequence, absl::Now() + kWait).ok());
}

// An upload whose seqs are those of an upload before it in the same group
// commit (a robot's retry queued behind its first try) is a duplicate only
// if that write succeeds: when it fails, both fail, and the robot keeps
// the traces. (Answered "duplicates", the robot dropped traces no log
// held: the cluster test's lost NATS server, 1 run in 20.)
TEST_F(WritePathTest, AGroupsFailedWriteFailsTheDuplicatesOfItsOwnUploads) {
  Open();
  ASSERT_TRUE(path_->Append("f", Traces("r1", 10, 2)).ok());  // the fleet
  const std::vector<core::MemoryTrace> traces = Traces("r1", 1, 4);
  const std::span<const core::MemoryTrace> twice[] = {traces, traces};
  store_.FailAppends(absl::UnavailableError("the log cannot be written"));
  std::vector<absl::StatusOr<Appended>> failed = path_->AppendMany("f", twice);
  ASSERT_EQ(failed.size(), 2u);
  EXPECT_EQ(failed[0].status().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(failed[1].status().code(), absl::StatusCode::kUnavailable)
      << "answered as duplicates of an upload that was not stored";

  store_.FailAppends(absl::OkStatus());
  std::vector<absl::StatusOr<Appended>> stored = path_->AppendMany("f", twice);
  ASSERT_TRUE(stored[0].ok() && stored[1].ok());
  EXPECT_EQ(stored[0]->accepted, 4u);
  EXPECT_EQ(stored[1]->duplicates, 4u);
  ASSERT_TRUE(path_->WaitAppliedAll("f", absl::Now() + kWait).ok());
  EXPECT_EQ(Held("f"), 6u);
}

// Distributed mode's owner (WritePathOptions::replicated): the write path
// admits against the log's tail it reads back when the fleet is taken,
// cuts uploads into the entries the cut gives, applies nothing itself (the
// owner's Materialiser does, and says how far: Applied), and refuses
// uploads once the fleet is lost.
WritePathOptions OwnerOptions() {
  WritePathOptions options;
  options.max_backlog_traces = 8;
  options.replicated = WritePathOptions::Replicated{[](std::span<
                                                        const core::MemoryTrace>
                                                           traces)
                                                        -> absl::StatusOr<
                                                            std::vector<
                                                                LogPiece>> {
    // One entry per trace, its id the robot and seq.
    std::vector<LogPiece> pieces;
    for (const core::MemoryTrace& trace : traces) {
      pieces.push_back({{trace}, absl::StrCat(trace.robot_id, "/", trace.seq)});
    }
    return pieces;
  }};
  return options;
}

TEST_F(WritePathTest, AnOwnersWritePathAdmitsAgainstTheTailItTookOver) {
  // The fleet's first upload, appended by the replica that created it (as
  // cluster::Ingest does), before this replica owns the fleet.
  const std::vector<core::MemoryTrace> first = Traces("r1", 1, 3);
  const LogAppend created{UploadRecord{first}, "created"};
  ASSERT_TRUE(log_->Append("f", {&created, 1}, {}).ok());
  Open(OwnerOptions());
  EXPECT_EQ(path_->Append("f", Traces("r1", 4, 1)).status().code(),
            absl::StatusCode::kUnavailable);  // not owned yet
  EXPECT_EQ(path_->Own("g", 0).code(), absl::StatusCode::kFailedPrecondition);

  ASSERT_TRUE(path_->Own("f", 0).ok());
  Backlog backlog = path_->GetBacklog("f");
  EXPECT_EQ(backlog.entries, 1u);  // the creating entry, not applied
  EXPECT_EQ(backlog.traces, 3u);
  // 2 and 3 are in the tail: duplicates; 4 and 5 are new, one entry each.
  absl::StatusOr<Appended> appended = path_->Append("f", Traces("r1", 2, 4));
  ASSERT_TRUE(appended.ok()) << appended.status();
  EXPECT_EQ(appended->accepted, 2u);
  EXPECT_EQ(appended->duplicates, 2u);
  EXPECT_EQ(appended->sequence, 3u);  // entries 2 and 3
  EXPECT_EQ(store_.appended_entries().back(), 2u);
  absl::StatusOr<std::vector<LogEntry>> read = log_->Read("f", 1, 10);
  ASSERT_TRUE(read.ok());
  ASSERT_EQ(read->size(), 2u);
  EXPECT_EQ(read->front().traces().front().seq, 4u);
  // Nothing is applied here: the owner applies.
  EXPECT_EQ(Held("f"), 0u);
  // The backlog bound (8) counts the tail taken over: 5 held unapplied.
  EXPECT_EQ(path_->Append("f", Traces("r1", 6, 4)).status().code(),
            absl::StatusCode::kResourceExhausted);
  // The owner applied entries 1 and 2: an upload's traces count until its
  // last entry is applied.
  path_->Applied("f", 2);
  backlog = path_->GetBacklog("f");
  EXPECT_EQ(backlog.traces, 2u);
  EXPECT_EQ(backlog.applied_through, 2u);
  path_->Applied("f", 3);
  EXPECT_EQ(path_->GetBacklog("f").traces, 0u);
  ASSERT_TRUE(path_->Append("f", Traces("r1", 6, 4)).ok());

  // Lost: uploads are refused until the fleet is owned again; the tail is
  // read back then.
  path_->Disown("f");
  EXPECT_EQ(path_->Append("f", Traces("r1", 10, 1)).status().code(),
            absl::StatusCode::kUnavailable);
  ASSERT_TRUE(path_->Own("f", 2).ok());
  absl::StatusOr<Appended> again = path_->Append("f", Traces("r1", 5, 5));
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->accepted, 0u);  // 5..9: all in the tail
  EXPECT_EQ(again->duplicates, 5u);
  EXPECT_EQ(path_->GetBacklog("f").traces, 5u);
}

}  // namespace
}  // namespace fleetmem::engine
