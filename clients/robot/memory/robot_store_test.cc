#include "clients/robot/memory/robot_store.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <thread>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/common/files.h"

namespace fleetmem::robot {
namespace {

using ::testing::HasSubstr;

const RobotIdentity kIdentity{
    .robot_id = "r1", .fleet_id = "f1", .source = "nordland:/x"};

class RobotStoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = temp_.Join("store");  // made by the code under test
  }

  std::unique_ptr<RobotStore> Open(RobotStoreOptions options = {}) {
    absl::StatusOr<std::unique_ptr<RobotStore>> store =
        RobotStore::Open(dir_, kIdentity, options);
    EXPECT_TRUE(store.ok()) << store.status();
    return store.ok() ? *std::move(store) : nullptr;
  }

  static v1::MemoryTrace Observed(uint64_t index) {
    v1::MemoryTrace trace;
    trace.set_robot_id("r1");
    trace.add_code(static_cast<float>(index));
    trace.add_code(1.0f);
    trace.mutable_pose()->set_x(static_cast<double>(index));
    return trace;
  }

  // Records observations [from, to) and seals them.
  static void Segment(RobotStore& store, uint64_t from, uint64_t to) {
    std::vector<v1::MemoryTrace> traces;
    for (uint64_t i = from; i < to; ++i) {
      ASSERT_TRUE(store.RecordObservation(i, Observed(i)).ok());
      traces.push_back(Observed(i));
    }
    ASSERT_TRUE(store.SealSegment(traces).ok());
  }

  files::TempDir temp_{"fleetmem-robot-store-"};
  std::string dir_;
};

TEST_F(RobotStoreTest, SeqsAreNeverReusedAfterARestart) {
  {
    std::unique_ptr<RobotStore> store = Open();
    ASSERT_TRUE(store && store->created());
    Segment(*store, 0, 3);
    EXPECT_EQ(store->state().next_seq(), 4u);
  }
  std::unique_ptr<RobotStore> store = Open();
  ASSERT_TRUE(store);
  EXPECT_FALSE(store->created());
  EXPECT_EQ(store->state().next_seq(), 4u);
  EXPECT_EQ(store->state().next_index(), 3u);
  Segment(*store, 3, 5);
  absl::StatusOr<std::vector<v1::MemoryTrace>> queued = store->PeekQueue(100);
  ASSERT_TRUE(queued.ok());
  ASSERT_EQ(queued->size(), 5u);
  for (size_t i = 0; i < queued->size(); ++i) {
    EXPECT_EQ((*queued)[i].seq(), i + 1);
    EXPECT_EQ((*queued)[i].pose().x(), static_cast<double>(i));
  }
  // Acknowledged traces leave; the seq counter does not go back.
  ASSERT_TRUE(store->MarkUploaded(5, 5, 0).ok());
  EXPECT_EQ(store->queue().depth, 0u);
  EXPECT_EQ(store->state().traces_uploaded(), 5u);
  EXPECT_EQ(store->SetFirstSeq(1).code(),
            absl::StatusCode::kFailedPrecondition);
  store.reset();
  store = Open();
  Segment(*store, 5, 6);
  EXPECT_EQ((*store->PeekQueue(1))[0].seq(), 6u);
}

TEST_F(RobotStoreTest, AFirstStartCanContinueAfterTheServersSeqs) {
  std::unique_ptr<RobotStore> store = Open();
  ASSERT_TRUE(store->SetFirstSeq(1001).ok());
  Segment(*store, 0, 2);
  EXPECT_EQ((*store->PeekQueue(1))[0].seq(), 1001u);
}

TEST_F(RobotStoreTest, TheOpenSegmentAndPositionSurviveAReopen) {
  {
    std::unique_ptr<RobotStore> store = Open();
    ASSERT_TRUE(store->RecordObservation(0, Observed(0)).ok());
    ASSERT_TRUE(store->RecordObservation(1, Observed(1)).ok());
    // Not the next observation: refused.
    EXPECT_EQ(store->RecordObservation(5, Observed(5)).code(),
              absl::StatusCode::kFailedPrecondition);
  }
  std::unique_ptr<RobotStore> store = Open();
  EXPECT_EQ(store->state().next_index(), 2u);
  absl::StatusOr<std::vector<StoredTrace>> open = store->OpenSegment();
  ASSERT_TRUE(open.ok());
  ASSERT_EQ(open->size(), 2u);
  EXPECT_EQ((*open)[1].source_index(), 1u);
  EXPECT_EQ(store->SealSegment({Observed(0)}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(RobotStoreTest, SealedTracesKeepTheirSourceIndexAfterTheUpload) {
  {
    std::unique_ptr<RobotStore> store = Open();
    ASSERT_TRUE(store);
    ASSERT_TRUE(store->SetFirstSeq(10).ok());  // after the server's seqs
    Segment(*store, 0, 3);                     // seqs 10..12
    Segment(*store, 3, 5);                     // seqs 13..14
    ASSERT_TRUE(store->MarkUploaded(14, 5, 0).ok());
    EXPECT_EQ(store->queue().depth, 0u);
  }
  std::unique_ptr<RobotStore> store = Open();
  ASSERT_TRUE(store);
  absl::StatusOr<std::vector<SourceIndex>> all = store->SourceIndices(0, 100);
  ASSERT_TRUE(all.ok()) << all.status();
  std::vector<std::pair<uint64_t, uint64_t>> pairs;
  for (const SourceIndex& s : *all) pairs.push_back({s.seq, s.index});
  using Pair = std::pair<uint64_t, uint64_t>;
  EXPECT_THAT(pairs,
              ::testing::ElementsAre(Pair{10, 0}, Pair{11, 1}, Pair{12, 2},
                                     Pair{13, 3}, Pair{14, 4}));
  absl::StatusOr<std::vector<SourceIndex>> page = store->SourceIndices(11, 2);
  ASSERT_TRUE(page.ok());
  ASSERT_EQ(page->size(), 2u);
  EXPECT_EQ((*page)[0].seq, 12u);
  EXPECT_EQ((*page)[1].seq, 13u);
}

TEST_F(RobotStoreTest, ADiscardedOpenSegmentIsObservedAgainFromItsStart) {
  std::unique_ptr<RobotStore> store = Open();
  ASSERT_TRUE(store);
  Segment(*store, 0, 2);
  ASSERT_TRUE(store->RecordObservation(2, Observed(2)).ok());
  ASSERT_TRUE(store->RecordObservation(3, Observed(3)).ok());
  EXPECT_EQ(store->state().next_index(), 4u);
  ASSERT_TRUE(store->DiscardOpenSegment().ok());
  EXPECT_EQ(store->state().next_index(), 2u);
  EXPECT_EQ(store->state().observations(), 2u);
  EXPECT_EQ(store->queue().open_segment, 0u);
  EXPECT_EQ(store->queue().depth, 2u);
  ASSERT_TRUE(store->DiscardOpenSegment().ok());  // nothing open: no change
  EXPECT_EQ(store->state().next_index(), 2u);
  store.reset();
  store = Open();
  ASSERT_TRUE(store);
  EXPECT_EQ(store->state().next_index(), 2u);
  EXPECT_TRUE(store->RecordObservation(2, Observed(2)).ok());
}

TEST_F(RobotStoreTest, AnotherRobotsDirIsRefused) {
  { ASSERT_TRUE(Open()); }
  absl::StatusOr<std::unique_ptr<RobotStore>> other = RobotStore::Open(
      dir_, {.robot_id = "r2", .fleet_id = "f1", .source = "nordland:/x"}, {});
  ASSERT_EQ(other.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(other.status().message(), HasSubstr("robot \"r1\""));
}

TEST_F(RobotStoreTest, AFullQueueRefusesObservationsAndChangesNothing) {
  std::unique_ptr<RobotStore> store =
      Open({.max_bytes = 400, .full_policy = FullPolicy::kRefuse});
  uint64_t index = 0;
  absl::Status status;
  while ((status = store->RecordObservation(index, Observed(index))).ok()) {
    ++index;
  }
  ASSERT_EQ(status.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(status.message(), HasSubstr("upload queue full"));
  EXPECT_EQ(store->state().next_index(), index);
  std::vector<v1::MemoryTrace> traces;
  for (uint64_t i = 0; i < index; ++i) traces.push_back(Observed(i));
  ASSERT_TRUE(store->SealSegment(traces).ok());
  EXPECT_EQ(store->RecordObservation(index, Observed(index)).code(),
            absl::StatusCode::kResourceExhausted);
  // Draining makes room again.
  ASSERT_TRUE(store->MarkUploaded(index, index, 0).ok());
  EXPECT_TRUE(store->RecordObservation(index, Observed(index)).ok());
  EXPECT_EQ(store->state().traces_dropped(), 0u);
}

TEST_F(RobotStoreTest, DropOldestMakesRoomAndCountsWhatItDropped) {
  std::unique_ptr<RobotStore> store =
      Open({.max_bytes = 600, .full_policy = FullPolicy::kDropOldest});
  for (uint64_t s = 0; s < 10; ++s) Segment(*store, s * 4, s * 4 + 4);
  EXPECT_LE(store->queue().bytes, 600u);
  const RobotState state = store->state();
  EXPECT_GT(state.traces_dropped(), 0u);
  EXPECT_EQ(state.traces_queued(), 40u);
  EXPECT_EQ(store->queue().depth + state.traces_dropped(), 40u);
  // What is left is the newest, still in order.
  absl::StatusOr<std::vector<v1::MemoryTrace>> queued = store->PeekQueue(100);
  EXPECT_EQ(queued->back().seq(), 40u);
  EXPECT_EQ(queued->front().seq(), state.traces_dropped() + 1);
}

TEST_F(RobotStoreTest, TheDiskReserveRefusesNewDataButNotRemovals) {
  uint64_t free = 100u << 20;
  std::unique_ptr<RobotStore> store = Open(
      {.min_free_bytes = 64u << 20, .free_bytes = [&free] { return free; }});
  Segment(*store, 0, 3);
  free = (64u << 20) + 10;  // less than the reserve plus twice a trace
  const absl::Status refused = store->RecordObservation(3, Observed(3));
  EXPECT_EQ(refused.code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(refused.message(), HasSubstr("disk nearly full"));
  EXPECT_THAT(refused.message(), HasSubstr("observation 3 was not recorded"));
  EXPECT_EQ(store->state().next_index(), 3u);
  // Uploaded traces still leave (that is how space comes back).
  EXPECT_TRUE(store->MarkUploaded(3, 3, 0).ok());
  EXPECT_EQ(store->queue().depth, 0u);
  free = 100u << 20;
  EXPECT_TRUE(store->RecordObservation(3, Observed(3)).ok());
}

// The child records and seals observations as fast as it can until it is
// SIGKILLed; the reopened store must be consistent: the position counts
// every recorded observation once, seqs are 1..next_seq-1 without a gap,
// each queued trace is the observation its seq says, and the open segment
// holds exactly the observations after the last sealed one.
TEST_F(RobotStoreTest, StaysConsistentWhenTheProcessIsKilled) {
  for (int trial = 0; trial < 3; ++trial) {
    const pid_t child = fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
      absl::StatusOr<std::unique_ptr<RobotStore>> store =
          RobotStore::Open(dir_, kIdentity, {});
      if (!store.ok()) _exit(2);
      uint64_t index = (*store)->state().next_index();
      while (true) {
        if (!(*store)->RecordObservation(index, Observed(index)).ok()) _exit(3);
        ++index;
        if (index % 7 == 0) {
          absl::StatusOr<std::vector<StoredTrace>> open =
              (*store)->OpenSegment();
          std::vector<v1::MemoryTrace> traces;
          for (const StoredTrace& stored : *open) {
            traces.push_back(stored.trace());
          }
          if (!(*store)->SealSegment(traces).ok()) _exit(4);
        }
      }
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(300 + 97 * trial));
    ASSERT_EQ(kill(child, SIGKILL), 0);
    int wstatus = 0;
    ASSERT_EQ(waitpid(child, &wstatus, 0), child);
    ASSERT_TRUE(WIFSIGNALED(wstatus)) << "child exited " << wstatus;

    std::unique_ptr<RobotStore> store = Open();
    ASSERT_TRUE(store);
    const RobotState state = store->state();
    ASSERT_GT(state.next_index(), 0u) << "trial " << trial;
    EXPECT_EQ(state.observations(), state.next_index());
    absl::StatusOr<std::vector<v1::MemoryTrace>> queued =
        store->PeekQueue(1u << 30);
    absl::StatusOr<std::vector<StoredTrace>> open = store->OpenSegment();
    ASSERT_TRUE(queued.ok() && open.ok());
    ASSERT_EQ(queued->size(), state.next_seq() - 1);
    ASSERT_EQ(queued->size() + open->size(), state.next_index());
    for (size_t i = 0; i < queued->size(); ++i) {
      ASSERT_EQ((*queued)[i].seq(), i + 1);
      ASSERT_EQ((*queued)[i].pose().x(), static_cast<double>(i));
    }
    for (size_t i = 0; i < open->size(); ++i) {
      ASSERT_EQ((*open)[i].source_index(), queued->size() + i);
    }
    EXPECT_EQ(store->queue().depth, queued->size());
  }
}

}  // namespace
}  // namespace fleetmem::robot
