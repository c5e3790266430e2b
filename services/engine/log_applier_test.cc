#include "services/engine/log_applier.h"

#include <memory>
#include <random>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "services/engine/memory_engine.h"
#include "services/storage/in_memory_log.h"
#include "services/storage/in_memory_store.h"
#include "services/testing/memory_engine_test_util.h"

namespace fleetmem::engine {
namespace {

// The robot's traces `first_seq`.. (codes of `dimension`), seeded by
// `first_seq`.
std::vector<core::MemoryTrace> Traces(const std::string& robot_id,
                                      uint64_t first_seq, size_t count,
                                      size_t dimension = kDimension) {
  std::mt19937_64 rng(first_seq);
  std::vector<core::MemoryTrace> traces;
  for (size_t i = 0; i < count; ++i) {
    traces.push_back(MakeTrace(robot_id, first_seq + i, rng, 1.0f, dimension));
  }
  return traces;
}

class LogApplyTest : public ::testing::Test {
 protected:
  std::unique_ptr<MemoryEngine> OpenEngine(MemoryStore* store) {
    EngineOptions options;
    options.memory.clusters_per_batch = 2;
    options.segment_size = 10;
    return OpenOn(options, store);
  }
  uint64_t Held(MemoryEngine& engine) {
    absl::StatusOr<FleetStats> stats = engine.GetStats("f");
    return stats.ok() ? stats->traces + stats->pending_traces : 0;
  }

  std::unique_ptr<MemoryStore> inner_ = storage::NewInMemoryStore();
  FlakyStore store_{inner_.get()};
};

TEST_F(LogApplyTest, AnUploadIsStoredUnderItsSequenceAndAgainChangesNothing) {
  std::unique_ptr<MemoryEngine> engine = OpenEngine(&store_);
  ASSERT_NE(engine, nullptr);
  const std::vector<core::MemoryTrace> traces = Traces("r1", 1, 12);
  absl::StatusOr<AppliedRecord> first =
      ApplyLogRecord(*engine, "f", 7, UploadRecord{traces});
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_TRUE(first->refused.ok());
  EXPECT_EQ(first->consolidations, 1u);  // 12 traces fill a segment of 10
  EXPECT_EQ(first->duplicates, 0u);
  EXPECT_EQ(engine->LogPosition("f").value_or(0), 7u);
  EXPECT_EQ(Held(*engine), 12u);

  absl::StatusOr<AppliedRecord> again =
      ApplyLogRecord(*engine, "f", 7, UploadRecord{traces});
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_EQ(again->duplicates, 12u);
  EXPECT_EQ(again->consolidations, 0u);
  EXPECT_EQ(Held(*engine), 12u);
}

// Refused by the fleet's state: every replica refuses it alike, so the
// entry is passed (OK, with the refusal); the log moves on.
TEST_F(LogApplyTest, AnEntryTheFleetsStateRefusesIsPassedWithItsRefusal) {
  std::unique_ptr<MemoryEngine> engine = OpenEngine(&store_);
  ASSERT_NE(engine, nullptr);
  absl::StatusOr<AppliedRecord> consolidated =
      ApplyLogRecord(*engine, "f", 1, ConsolidateRecord{});
  ASSERT_TRUE(consolidated.ok()) << consolidated.status();
  EXPECT_EQ(consolidated->refused.code(), absl::StatusCode::kNotFound)
      << consolidated->refused;

  ASSERT_TRUE(
      ApplyLogRecord(*engine, "f", 2, UploadRecord{Traces("r1", 1, 4)}).ok());
  const std::vector<core::MemoryTrace> wider =
      Traces("r2", 1, 4, 2 * kDimension);
  absl::StatusOr<AppliedRecord> refused =
      ApplyLogRecord(*engine, "f", 3, UploadRecord{wider});
  ASSERT_TRUE(refused.ok()) << refused.status();
  EXPECT_EQ(refused->refused.code(), absl::StatusCode::kInvalidArgument)
      << refused->refused;
  EXPECT_EQ(Held(*engine), 4u);
}

// The store's errors are returned, not passed: a full disk must not lose
// the entry on this replica; applied again later, it applies.
TEST_F(LogApplyTest, TheStoresErrorIsReturnedAndTheEntryAppliesLater) {
  std::unique_ptr<MemoryEngine> engine = OpenEngine(&store_);
  ASSERT_NE(engine, nullptr);
  const std::vector<core::MemoryTrace> traces = Traces("r1", 1, 4);
  store_.fail_after = store_.applies;
  store_.failure = absl::ResourceExhaustedError("disk nearly full");
  absl::StatusOr<AppliedRecord> failed =
      ApplyLogRecord(*engine, "f", 1, UploadRecord{traces});
  EXPECT_EQ(failed.status().code(), absl::StatusCode::kResourceExhausted);
  store_.fail_after = -1;
  absl::StatusOr<AppliedRecord> applied =
      ApplyLogRecord(*engine, "f", 1, UploadRecord{traces});
  ASSERT_TRUE(applied.ok()) << applied.status();
  EXPECT_EQ(applied->duplicates, 0u);
  EXPECT_EQ(Held(*engine), 4u);
}

// Two engines that apply the same entries reach the same answers: the
// consolidation and the sample drawn under the entry's sequence.
TEST_F(LogApplyTest, TwoEnginesApplyingTheSameEntriesAnswerAlike) {
  std::unique_ptr<MemoryStore> other_store = storage::NewInMemoryStore();
  std::unique_ptr<MemoryEngine> a = OpenEngine(&store_);
  std::unique_ptr<MemoryEngine> b = OpenEngine(other_store.get());
  ASSERT_NE(a, nullptr);
  ASSERT_NE(b, nullptr);
  const std::vector<core::MemoryTrace> r1 = Traces("r1", 1, 12);
  const std::vector<core::MemoryTrace> r2 = Traces("r2", 1, 7);
  const std::vector<LogRecord> log = {
      UploadRecord{r1}, UploadRecord{r2}, ConsolidateRecord{},
      SampleReplayRecord{.robot_id = "r1", .count = 5, .request_id = "q1"}};
  std::vector<AppliedRecord> answers[2];
  for (uint64_t sequence = 1; sequence <= log.size(); ++sequence) {
    for (int replica = 0; replica < 2; ++replica) {
      absl::StatusOr<AppliedRecord> applied = ApplyLogRecord(
          replica == 0 ? *a : *b, "f", sequence, log[sequence - 1]);
      ASSERT_TRUE(applied.ok()) << applied.status();
      ASSERT_TRUE(applied->refused.ok()) << applied->refused;
      answers[replica].push_back(*std::move(applied));
    }
  }
  EXPECT_EQ(answers[0][0].consolidations, 1u);  // a segment of r1's
  EXPECT_EQ(answers[1][0].consolidations, 1u);
  EXPECT_GT(answers[0][2].consolidated.consolidated_traces, 0u);
  EXPECT_EQ(answers[0][2].consolidated.consolidated_traces,
            answers[1][2].consolidated.consolidated_traces);
  EXPECT_EQ(answers[0][2].consolidated.clusters,
            answers[1][2].consolidated.clusters);
  ASSERT_EQ(answers[0][3].sample.size(), 5u);
  ASSERT_EQ(answers[1][3].sample.size(), 5u);
  for (size_t i = 0; i < 5; ++i) {
    EXPECT_EQ(answers[0][3].sample[i].robot_id,
              answers[1][3].sample[i].robot_id);
    EXPECT_EQ(answers[0][3].sample[i].seq, answers[1][3].sample[i].seq);
  }
}

// A turn applies the entries after the position in order, stops before an
// entry its hook refuses and at a store error (the entry stays unapplied),
// and passes an entry the state refuses; the next turn goes on from the
// position it returned.
TEST_F(LogApplyTest, ATurnAppliesInOrderAndStopsWhereItIsTold) {
  std::unique_ptr<MemoryEngine> engine = OpenEngine(&store_);
  ASSERT_NE(engine, nullptr);
  std::unique_ptr<FleetLog> log = storage::NewInMemoryLog();
  const std::vector<core::MemoryTrace> a = Traces("r1", 1, 4);
  const std::vector<core::MemoryTrace> wrong = Traces("r1", 5, 2, 3);
  const std::vector<core::MemoryTrace> b = Traces("r2", 1, 4);
  const LogAppend appends[] = {
      {UploadRecord{a}}, {UploadRecord{wrong}}, {UploadRecord{b}}};
  ASSERT_TRUE(log->Append("f", appends, {}).ok());
  LogApplier applier(log.get(), engine.get());

  std::vector<uint64_t> told;
  ApplyHooks hooks;
  hooks.may_apply = [](const LogEntry& entry) { return entry.sequence < 3; };
  hooks.applied = [&](const LogEntry& entry, const AppliedRecord& applied) {
    told.push_back(entry.sequence);
    if (entry.sequence == 2) {
      EXPECT_EQ(applied.refused.code(), absl::StatusCode::kInvalidArgument);
    }
  };
  absl::StatusOr<AppliedTurn> turn = applier.Turn("f", 0, 10, hooks);
  ASSERT_TRUE(turn.ok()) << turn.status();
  EXPECT_EQ(turn->position, 2u);
  EXPECT_EQ(turn->applied, 2u);
  EXPECT_TRUE(turn->stopped.ok());
  EXPECT_EQ(told, (std::vector<uint64_t>{1, 2}));
  EXPECT_EQ(Held(*engine), 4u);

  store_.fail_after = store_.applies;
  store_.failure = absl::ResourceExhaustedError("disk nearly full");
  turn = applier.Turn("f", 2, 10);
  ASSERT_TRUE(turn.ok()) << turn.status();
  EXPECT_EQ(turn->position, 2u);
  EXPECT_EQ(turn->stopped.code(), absl::StatusCode::kResourceExhausted);
  store_.fail_after = -1;
  turn = applier.Turn("f", turn->position, 10);
  ASSERT_TRUE(turn.ok()) << turn.status();
  EXPECT_EQ(turn->position, 3u);
  EXPECT_EQ(Held(*engine), 8u);
  EXPECT_EQ(engine->LogPosition("f").value_or(0), 3u);
}

}  // namespace
}  // namespace fleetmem::engine
