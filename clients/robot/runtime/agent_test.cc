// The agent's loop without a server (the address refuses connections): the
// segments, the learner hook, the durable queue and position. The agent
// against the real server is tested in tests/robot_integration_test.cc.
#include "clients/robot/runtime/agent.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "clients/robot/sensing/encoder_factory.h"
#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/common/files.h"

namespace fleetmem::robot {
namespace {

using ::testing::ElementsAre;

const std::string kSummer = std::string(FLEETMEM_DATA_DIR) + "/nordland/summer";

class RecordingLearner : public Learner {
 public:
  absl::StatusOr<std::string> Learn(
      std::span<const core::MemoryTrace> segment,
      std::span<const Observation> observations,
      std::span<const core::MemoryTrace> replayed,
      std::span<const core::MemoryTrace>) override {
    std::vector<size_t> indices;
    EXPECT_EQ(segment.size(), observations.size());
    for (size_t i = 0; i < observations.size(); ++i) {
      indices.push_back(observations[i].index);
      EXPECT_FALSE(observations[i].image.empty());
      // The trace is the observation's: its place and its code.
      EXPECT_EQ(segment[i].place.x, observations[i].place.x);
      EXPECT_FALSE(segment[i].code.empty());
    }
    segments.push_back(indices);
    replayed_sizes.push_back(replayed.size());
    return std::string("learned");
  }
  std::vector<std::vector<size_t>> segments;
  std::vector<size_t> replayed_sizes;
};

class AgentTest : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = temp_.Join("robot");  // made by the code under test
    absl::StatusOr<std::unique_ptr<ObservationSource>> source =
        OpenNordlandFolder(kSummer);
    ASSERT_TRUE(source.ok()) << source.status();
    source_ = *std::move(source);
    absl::StatusOr<std::unique_ptr<Encoder>> encoder =
        NewEncoderByName(source_->default_encoder());
    ASSERT_TRUE(encoder.ok());
    encoder_ = *std::move(encoder);
    client::ClientOptions client_options;
    client_options.target = "127.0.0.1:1";  // nothing listens there
    client_options.max_attempts = 1;
    client_options.deadline = std::chrono::milliseconds(500);
    client_ = client::Client::Create(client_options);
  }

  std::unique_ptr<RobotStore> OpenStore(RobotStoreOptions options = {}) {
    absl::StatusOr<std::unique_ptr<RobotStore>> store = RobotStore::Open(
        dir_, {.robot_id = "r1", .fleet_id = "f1", .source = "s"}, options);
    EXPECT_TRUE(store.ok()) << store.status();
    return store.ok() ? *std::move(store) : nullptr;
  }

  AgentOptions Options(size_t first, size_t last) {
    AgentOptions options;
    options.fleet_id = "f1";
    options.robot_id = "r1";
    options.domain = "summer";
    options.segment_size = 4;
    options.first = first;
    options.last = last;
    options.relocalise = false;
    options.drain_timeout = std::chrono::milliseconds(0);
    options.status_file = dir_ + "/status.json";
    options.log = [](std::string_view) {};
    return options;
  }

  files::TempDir temp_{"fleetmem-agent-"};
  std::string dir_;
  std::unique_ptr<ObservationSource> source_;
  std::unique_ptr<Encoder> encoder_;
  std::unique_ptr<client::Client> client_;
};

TEST_F(AgentTest, QueuesEverySegmentWhileTheServerIsAwayAndResumes) {
  std::atomic<bool> stop{false};
  {
    std::unique_ptr<RobotStore> store = OpenStore();
    RecordingLearner learner;
    Agent agent(Options(100, 110), client_.get(), client_.get(), source_.get(),
                encoder_.get(), store.get(), &learner);
    // The source ends; the queue cannot drain (no server) and is kept.
    EXPECT_TRUE(agent.Run(stop).ok());
    const AgentSummary summary = agent.summary();
    EXPECT_TRUE(summary.source_finished);
    EXPECT_FALSE(summary.drained);
    EXPECT_EQ(summary.queue.depth, 10u);
    EXPECT_EQ(summary.state.next_seq(), 11u);
    EXPECT_EQ(summary.state.segments(), 3u);
    // Segments of 4, 4 and the last 2, each handed to the learner with its
    // real observations; nothing to replay without a fleet.
    EXPECT_THAT(learner.segments, ElementsAre(ElementsAre(100, 101, 102, 103),
                                              ElementsAre(104, 105, 106, 107),
                                              ElementsAre(108, 109)));
    // The robot's own traces fill its dynamic memory: later segments replay.
    EXPECT_THAT(learner.replayed_sizes, ElementsAre(0, 4, 8));
  }
  // Every queued trace carries the encoder's version, a seq, a place and
  // its rewards.
  std::unique_ptr<RobotStore> store = OpenStore();
  absl::StatusOr<std::vector<v1::MemoryTrace>> queued = store->PeekQueue(100);
  ASSERT_TRUE(queued.ok());
  ASSERT_EQ(queued->size(), 10u);
  for (size_t i = 0; i < queued->size(); ++i) {
    const v1::MemoryTrace& trace = (*queued)[i];
    EXPECT_EQ(trace.seq(), i + 1);
    EXPECT_EQ(trace.encoder_version(), encoder_->version());
    EXPECT_EQ(trace.code_size(), static_cast<int>(encoder_->dimension()));
    EXPECT_EQ(trace.pose().x(), 10.0 * (101 + i));  // images-01010.png, ...
    EXPECT_EQ(trace.domain(), "summer");
    EXPECT_FLOAT_EQ(trace.reward(),
                    trace.reward_external() + trace.reward_internal());
    EXPECT_GT(trace.reward_internal(), 0.0f);
  }
  // A second run with a longer range resumes after observation 109.
  RecordingLearner learner;
  Agent agent(Options(100, 114), client_.get(), client_.get(), source_.get(),
              encoder_.get(), store.get(), &learner);
  EXPECT_TRUE(agent.Run(stop).ok());
  EXPECT_EQ(agent.summary().observed_this_run, 4u);
  EXPECT_THAT(learner.segments, ElementsAre(ElementsAre(110, 111, 112, 113)));
  EXPECT_EQ(agent.summary().state.next_seq(), 15u);
}

// With no server, the uploader opens a new connection after every
// reconnect_after_failures failed uploads (a TLS channel of gRPC 1.51 may
// never recover otherwise), and logs it; the queue is kept.
TEST_F(AgentTest, TheUploaderReopensItsConnectionAfterFailuresInARow) {
  std::atomic<bool> stop{false};
  std::unique_ptr<RobotStore> store = OpenStore();
  RecordingLearner learner;
  AgentOptions options = Options(100, 104);
  options.initial_backoff = std::chrono::milliseconds(1);
  options.max_backoff = std::chrono::milliseconds(1);
  options.drain_timeout = std::chrono::milliseconds(1500);
  options.reconnect_after_failures = 3;
  std::atomic<int> created{0};
  options.new_upload_client = [&created] {
    ++created;
    client::ClientOptions unreachable;
    unreachable.target = "127.0.0.1:1";
    unreachable.max_attempts = 1;
    unreachable.deadline = std::chrono::milliseconds(100);
    return client::Client::Create(unreachable);
  };
  std::atomic<int> reopened{0};
  options.log = [&reopened](std::string_view line) {
    if (line.find("opened a new connection") != std::string_view::npos) {
      ++reopened;
    }
  };
  Agent agent(options, client_.get(), client_.get(), source_.get(),
              encoder_.get(), store.get(), &learner);
  EXPECT_TRUE(agent.Run(stop).ok());
  EXPECT_FALSE(agent.summary().drained);
  EXPECT_EQ(agent.summary().queue.depth, 4u);
  // The first client, then one more per 3 failures.
  EXPECT_GE(created.load(), 3);
  EXPECT_GE(reopened.load(), 2);
}

TEST_F(AgentTest, ALearnerErrorStopsTheRobotAndKeepsTheSegmentOpen) {
  class FailingLearner : public Learner {
    absl::StatusOr<std::string> Learn(
        std::span<const core::MemoryTrace>, std::span<const Observation>,
        std::span<const core::MemoryTrace>,
        std::span<const core::MemoryTrace>) override {
      return absl::InternalError("out of memory in training");
    }
  } learner;
  std::unique_ptr<RobotStore> store = OpenStore();
  Agent agent(Options(0, 10), client_.get(), client_.get(), source_.get(),
              encoder_.get(), store.get(), &learner);
  std::atomic<bool> stop{false};
  const absl::Status status = agent.Run(stop);
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
  EXPECT_EQ(store->queue().open_segment, 4u);
  EXPECT_EQ(store->queue().depth, 0u);
  EXPECT_EQ(store->state().next_index(), 4u);
  EXPECT_THAT(std::filesystem::exists(dir_ + "/status.json"), true);
}

// A HOG trace takes about 2.1 KB in the queue: room for about three.
constexpr uint64_t kThreeTraces = 7000;

TEST_F(AgentTest, AFullQueueStopsObservingWithALogLineAndDropsNothing) {
  std::unique_ptr<RobotStore> store = OpenStore(
      {.max_bytes = kThreeTraces, .full_policy = FullPolicy::kRefuse});
  AgentOptions options = Options(0, 50);
  options.segment_size = 2;
  std::vector<std::string> lines;
  absl::Mutex mu;
  options.log = [&](std::string_view line) {
    absl::MutexLock lock(&mu);
    lines.emplace_back(line);
  };
  Agent agent(options, client_.get(), client_.get(), source_.get(),
              encoder_.get(), store.get());
  std::atomic<bool> stop{false};
  absl::Status status;
  std::thread run([&] { status = agent.Run(stop); });
  std::this_thread::sleep_for(std::chrono::milliseconds(1500));
  stop = true;
  run.join();
  EXPECT_TRUE(status.ok()) << status;
  const AgentSummary summary = agent.summary();
  // It waits at the bound instead of dropping: 3 observations, no more.
  EXPECT_EQ(summary.state.next_index(), 3u);
  EXPECT_EQ(summary.state.traces_dropped(), 0u);
  EXPECT_LE(summary.queue.bytes, kThreeTraces);
  absl::MutexLock lock(&mu);
  EXPECT_THAT(lines,
              ::testing::Contains(::testing::HasSubstr("upload queue full: ")));
}

TEST_F(AgentTest, DropOldestKeepsObservingAndCountsWhatItDropped) {
  std::unique_ptr<RobotStore> store = OpenStore(
      {.max_bytes = kThreeTraces, .full_policy = FullPolicy::kDropOldest});
  AgentOptions options = Options(0, 10);
  options.segment_size = 2;
  Agent agent(options, client_.get(), client_.get(), source_.get(),
              encoder_.get(), store.get());
  std::atomic<bool> stop{false};
  EXPECT_TRUE(agent.Run(stop).ok());
  const AgentSummary summary = agent.summary();
  EXPECT_EQ(summary.state.next_index(), 10u);
  EXPECT_EQ(summary.state.traces_queued(), 10u);
  EXPECT_EQ(summary.queue.depth + summary.state.traces_dropped(), 10u);
  EXPECT_GE(summary.state.traces_dropped(), 6u);
  EXPECT_LE(summary.queue.bytes, kThreeTraces);
}

}  // namespace
}  // namespace fleetmem::robot
