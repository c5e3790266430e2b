// fleetmem-robot end to end: the real robot binary against the real server
// binary, both killed with SIGKILL at moments the test picks, on the real
// Nordland and laser recordings. Every check counts traces on the server by
// (robot_id, seq): RobotStats.received counts the traces the server
// accepted (a repeat of a stored (robot, seq) is a duplicate and not
// counted), max_seq the highest seq it got; received == max_seq == the
// observations made means none was lost and none stored twice.
#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <map>
#include <random>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "clients/robot/learning/gpl_model.h"
#include "clients/robot/learning/metric_head.h"
#include "clients/robot/memory/robot_state.pb.h"
#include "clients/robot/memory/robot_store.h"
#include "clients/robot/sensing/encoder_factory.h"
#include "clients/robot/sensing/observation_source.h"
#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "google/protobuf/util/json_util.h"
#include "gtest/gtest.h"
#include "services/core/place_metrics.h"
#include "tests/api_helpers.h"
#include "tests/server_process.h"
#include "tests/small_filesystem.h"

namespace fleetmem::testing {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using Clock = std::chrono::steady_clock;

const std::string kData = FLEETMEM_DATA_DIR;
const std::string kSummer = "nordland:" + kData + "/nordland/summer";
const std::string kLaser = "carmen:" + kData + "/laser/aces.clf.bz2";

// One run of fleetmem-robot (fork/exec; output appended to a log file; its
// own process group; SIGKILLed if the test thread dies).
class RobotProcess {
 public:
  RobotProcess(std::vector<std::string> args, std::string log)
      : args_(std::move(args)), log_(std::move(log)) {}
  ~RobotProcess() {
    if (pid_ > 0) Kill();
  }

  void Start() {
    std::vector<std::string> argv_strings = {std::string(FLEETMEM_BIN_DIR) +
                                             "/fleetmem-robot"};
    argv_strings.insert(argv_strings.end(), args_.begin(), args_.end());
    std::vector<char*> argv;
    for (std::string& arg : argv_strings) argv.push_back(arg.data());
    argv.push_back(nullptr);
    const int fd = open(log_.c_str(), O_WRONLY | O_CREAT | O_APPEND, 0644);
    ASSERT_GE(fd, 0) << log_;
    pid_ = fork();
    ASSERT_GE(pid_, 0);
    if (pid_ == 0) {
      setpgid(0, 0);
      prctl(PR_SET_PDEATHSIG, SIGKILL);
      dup2(fd, 1);
      dup2(fd, 2);
      execv(argv[0], argv.data());
      _exit(127);
    }
    close(fd);
  }
  void Kill() {
    kill(pid_, SIGKILL);
    Wait();
  }
  void Signal(int signal) { kill(pid_, signal); }
  // Exit code, or -signal.
  int Wait() {
    int status = 0;
    waitpid(pid_, &status, 0);
    pid_ = -1;
    return WIFEXITED(status) ? WEXITSTATUS(status) : -WTERMSIG(status);
  }
  bool running() const { return pid_ > 0; }
  pid_t pid() const { return pid_; }

 private:
  std::vector<std::string> args_;
  std::string log_;
  pid_t pid_ = -1;
};

robot::state::RobotStatus ReadStatus(const std::string& data_dir) {
  robot::state::RobotStatus status;
  const std::string json = ReadFileOrEmpty(data_dir + "/status.json");
  if (!json.empty()) {
    (void)google::protobuf::util::JsonStringToMessage(json, &status);
  }
  return status;
}

// A camera robot on Nordland and a laser robot on the ACES log, each in
// its own fleet (a fleet holds one encoder).
struct RobotCase {
  std::string fleet, robot, source, encoder_version;
  size_t observations;
};
std::vector<RobotCase> CameraAndLaser(const std::string& prefix) {
  return {
      {prefix + "-camera", "cam-1", kSummer, "hog-64x32-c8-s8-b6-v1", 2000},
      {prefix + "-laser", "laser-1", kLaser, "scanring-r32-d32-m20-v1", 1500}};
}

class RobotIntegrationTest : public ::testing::Test {
 protected:
  void SetUp() override {
    // Without the recordings every robot would stop at once and each check
    // would wait out its deadline: fail here instead, saying what is missing.
    for (const std::string& needed :
         {kData + "/nordland/summer", kData + "/laser/aces.clf.bz2"}) {
      ASSERT_TRUE(std::filesystem::exists(needed))
          << needed << " is missing: this test runs robots on the real data "
          << "(FLEETMEM_DATA_DIR, the checkout's ../shared/data by default)";
    }
    ASSERT_FALSE(dir_.path().empty());
    ASSERT_EQ(mkdir(dir_.Join("server").c_str(), 0755), 0);
    ASSERT_NO_FATAL_FAILURE(StartServer());
  }
  void TearDown() override {
    if (HasFailure()) {
      std::cerr << "---- server log ----\n"
                << ReadFileOrEmpty(dir_.Join("server.log")).substr(0, 20000)
                << "\n---- robot log ----\n"
                << ReadFileOrEmpty(dir_.Join("robot.log")).substr(0, 40000)
                << std::endl;
    }
    if (server_ && server_->running()) {
      absl::StatusOr<int> code = server_->Stop();
      EXPECT_TRUE(code.ok() && *code == 0);
    }
  }

  // (Re)starts the server on the same data dir and, after the first start,
  // the same port, so that robots find it again.
  void StartServer() {
    ServerOptions options;
    options.data_dir = dir_.Join("server");
    options.log_file = dir_.Join("server.log");
    options.listen =
        port_ == 0 ? "127.0.0.1:0" : absl::StrCat("127.0.0.1:", port_);
    server_ = std::make_unique<ServerProcess>(options);
    absl::Status started = server_->Start();
    ASSERT_TRUE(started.ok()) << started;
    port_ = server_->port();
  }

  std::string Address() const { return absl::StrCat("127.0.0.1:", port_); }

  std::vector<std::string> RobotArgs(const std::string& fleet,
                                     const std::string& robot_id,
                                     const std::string& source, size_t last,
                                     double rate, const std::string& data_dir) {
    return {"--server",        Address(),
            "--fleet",         fleet,
            "--robot-id",      robot_id,
            "--source",        source,
            "--data-dir",      data_dir,
            "--last",          absl::StrCat(last),
            "--rate",          absl::StrCat(rate),
            "--drain-timeout", "60",
            "--segment-size",  "100"};
  }

  // The robot's stats once the fleet's log is applied through everything
  // acknowledged: robots upload with durable acknowledgement, so a robot
  // that has finished may still have traces waiting to be applied.
  v1::RobotStats Stats(const std::string& fleet, const std::string& robot) {
    std::unique_ptr<v1::MemoryService::Stub> stub = MakeStub(Address());
    Reply<v1::GetStatsResponse> stats = GetStatsApplied(*stub, fleet);
    EXPECT_TRUE(stats.ok()) << Describe(stats.status);
    EXPECT_EQ(stats.response.backlog_traces(), 0u)
        << "the fleet's log was not applied within 120 s";
    const v1::RobotStats* found = FindRobot(stats.response, robot);
    return found == nullptr ? v1::RobotStats() : *found;
  }

  // Starts one robot per case, observing at `rate` Hz.
  std::vector<std::unique_ptr<RobotProcess>> StartRobots(
      const std::vector<RobotCase>& cases, double rate) {
    std::vector<std::unique_ptr<RobotProcess>> robots;
    for (const RobotCase& c : cases) {
      robots.push_back(std::make_unique<RobotProcess>(
          RobotArgs(c.fleet, c.robot, c.source, c.observations, rate,
                    dir_.Join(c.robot)),
          dir_.Join("robot.log")));
      robots.back()->Start();
      if (HasFatalFailure()) break;
    }
    return robots;
  }

  TempDir dir_{"fleetmem-robot-it-"};
  std::unique_ptr<ServerProcess> server_;
  int port_ = 0;
};

TEST_F(RobotIntegrationTest, ServerKilledTwiceWhileRobotsUpload) {
  const std::vector<RobotCase> cases = CameraAndLaser("server-kill");
  std::vector<std::unique_ptr<RobotProcess>> robots = StartRobots(cases, 250);
  std::mt19937 rng(std::random_device{}());
  for (int kill = 0; kill < 2; ++kill) {
    std::this_thread::sleep_for(std::chrono::milliseconds(
        std::uniform_int_distribution<int>(1500, 3000)(rng)));
    server_->Kill();
    std::this_thread::sleep_for(std::chrono::milliseconds(
        std::uniform_int_distribution<int>(200, 1500)(rng)));
    ASSERT_NO_FATAL_FAILURE(StartServer());
  }
  std::unique_ptr<v1::MemoryService::Stub> stub = MakeStub(Address());
  for (size_t i = 0; i < robots.size(); ++i) {
    const RobotCase& c = cases[i];
    EXPECT_EQ(robots[i]->Wait(), 0) << c.robot;
    const v1::RobotStats stats = Stats(c.fleet, c.robot);
    EXPECT_EQ(stats.received(), c.observations) << c.robot;
    EXPECT_EQ(stats.max_seq(), c.observations) << c.robot;
    const robot::state::RobotStatus status = ReadStatus(dir_.Join(c.robot));
    EXPECT_EQ(status.phase(), "done") << c.robot;
    EXPECT_EQ(status.queue_depth(), 0u) << c.robot;
    EXPECT_EQ(status.counters().traces_queued(), c.observations) << c.robot;
    // The encoder's version travelled with every trace.
    EXPECT_EQ(GetStats(*stub, c.fleet).response.encoder_version(),
              c.encoder_version);
  }
}

TEST_F(RobotIntegrationTest, SigtermStopsCleanlyAndARestartFinishes) {
  constexpr size_t kObservations = 600;
  const std::string data_dir = dir_.Join("r1");
  RobotProcess robot(
      RobotArgs("f-term", "r1", kSummer, kObservations, 150.0, data_dir),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(robot.Start());
  // Signal once the robot is observing, not after a fixed delay: a robot
  // that is still loading (slow under the sanitizers) has no handler yet.
  const auto deadline = Clock::now() + std::chrono::seconds(120);
  while (ReadStatus(data_dir).counters().observations() == 0) {
    ASSERT_LT(Clock::now(), deadline) << "the robot never started observing";
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  robot.Signal(SIGTERM);
  EXPECT_EQ(robot.Wait(), 0);
  const robot::state::RobotStatus stopped = ReadStatus(data_dir);
  EXPECT_EQ(stopped.phase(), "stopped");
  const uint64_t observed = stopped.counters().observations();
  EXPECT_GT(observed, 0u);
  EXPECT_LT(observed, kObservations);
  // Everything observed is uploaded or durable here.
  EXPECT_EQ(stopped.counters().traces_uploaded() + stopped.queue_depth() +
                stopped.open_segment(),
            observed);
  RobotProcess again(
      RobotArgs("f-term", "r1", kSummer, kObservations, 0.0, data_dir),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(again.Start());
  EXPECT_EQ(again.Wait(), 0);
  const v1::RobotStats stats = Stats("f-term", "r1");
  EXPECT_EQ(stats.received(), kObservations);
  EXPECT_EQ(stats.max_seq(), kObservations);
}

TEST_F(RobotIntegrationTest,
       RobotsKilledTwiceAndRestartedLoseAndRepeatNothing) {
  const std::vector<RobotCase> cases = CameraAndLaser("robot-kill");
  std::vector<std::unique_ptr<RobotProcess>> robots = StartRobots(cases, 300);
  std::mt19937 rng(std::random_device{}());
  // Each kill comes once every robot has observed more than before it (a
  // slow start, e.g. a VM that allocates slowly, would otherwise kill a
  // robot before it observed anything, and there is nothing to resume).
  std::vector<uint64_t> observed(cases.size(), 0);
  auto wait_for_progress = [&] {
    for (size_t i = 0; i < cases.size(); ++i) {
      const absl::Time deadline = absl::Now() + absl::Seconds(120);
      while (absl::Now() < deadline &&
             ReadStatus(dir_.Join(cases[i].robot)).counters().observations() <=
                 observed[i]) {
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
      }
      observed[i] =
          ReadStatus(dir_.Join(cases[i].robot)).counters().observations();
    }
  };
  for (int kill = 0; kill < 2; ++kill) {
    wait_for_progress();
    std::this_thread::sleep_for(std::chrono::milliseconds(
        std::uniform_int_distribution<int>(0, 1000)(rng)));
    for (auto& robot : robots) {
      robot->Kill();
      ASSERT_NO_FATAL_FAILURE(robot->Start());
    }
  }
  for (size_t i = 0; i < robots.size(); ++i) {
    EXPECT_EQ(robots[i]->Wait(), 0) << cases[i].robot;
    const v1::RobotStats stats = Stats(cases[i].fleet, cases[i].robot);
    EXPECT_EQ(stats.received(), cases[i].observations) << cases[i].robot;
    EXPECT_EQ(stats.max_seq(), cases[i].observations) << cases[i].robot;
    const robot::state::RobotStatus status =
        ReadStatus(dir_.Join(cases[i].robot));
    // Each observation was made once: the position and the count agree.
    EXPECT_EQ(status.counters().observations(), cases[i].observations);
    EXPECT_EQ(status.counters().next_index(), cases[i].observations);
    // The watch resumed from its durable cursor: every event id from 1 to
    // the cursor was counted exactly once.
    EXPECT_GT(status.counters().watch_cursor(), 0u);
    EXPECT_EQ(status.counters().events_seen(),
              status.counters().watch_cursor());
  }
  const std::string log = ReadFileOrEmpty(dir_.Join("robot.log"));
  EXPECT_THAT(log, HasSubstr("resuming at observation"));
}

TEST_F(RobotIntegrationTest, ServerDownFor30SecondsTheQueueGrowsThenDrains) {
  constexpr size_t kObservations = 1600;
  const std::string data_dir = dir_.Join("r1");
  RobotProcess robot(
      RobotArgs("f-outage", "r1", kSummer, kObservations, 40.0, data_dir),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(robot.Start());
  std::this_thread::sleep_for(std::chrono::seconds(4));
  server_->Kill();
  const auto down = Clock::now();
  uint64_t peak = 0;
  double oldest = 0.0;
  while (Clock::now() - down < std::chrono::seconds(30)) {
    std::this_thread::sleep_for(std::chrono::seconds(1));
    const robot::state::RobotStatus status = ReadStatus(data_dir);
    peak = std::max(peak, status.queue_depth());
    oldest = std::max(oldest, status.queue_oldest_age_s());
  }
  // 30 s at 40 Hz: about 1,200 observations, sealed every 100 and queued.
  EXPECT_GE(peak, 900u);
  EXPECT_GE(oldest, 15.0);
  ASSERT_NO_FATAL_FAILURE(StartServer());
  EXPECT_EQ(robot.Wait(), 0);
  const v1::RobotStats stats = Stats("f-outage", "r1");
  EXPECT_EQ(stats.received(), kObservations);
  EXPECT_EQ(stats.max_seq(), kObservations);
  EXPECT_EQ(ReadStatus(data_dir).queue_depth(), 0u);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("robot.log")),
              HasSubstr("server reachable again"));
}

// A robot's first start asks the server for its last seq: it waits for a
// server that is restarting, and gives up after --first-contact-timeout
// without having observed or written anything.
TEST_F(RobotIntegrationTest, AFirstStartWaitsForTheServerThenGivesUpCleanly) {
  server_->Kill();
  RobotProcess waiting(
      RobotArgs("f-first", "r1", kSummer, 200, 0.0, dir_.Join("r1")),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(waiting.Start());
  // Start the server once the robot has found it missing, not after a fixed
  // delay: under the sanitizers a robot can take longer than that to load.
  constexpr char kWaiting[] = "waiting for the server before a first start";
  const auto deadline = Clock::now() + std::chrono::seconds(120);
  while (ReadFileOrEmpty(dir_.Join("robot.log")).find(kWaiting) ==
         std::string::npos) {
    ASSERT_LT(Clock::now(), deadline) << "the robot never waited";
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ASSERT_NO_FATAL_FAILURE(StartServer());
  EXPECT_EQ(waiting.Wait(), 0);
  EXPECT_EQ(Stats("f-first", "r1").received(), 200u);

  server_->Kill();
  std::vector<std::string> args =
      RobotArgs("f-first", "r2", kSummer, 200, 0.0, dir_.Join("r2"));
  args.insert(args.end(), {"--first-contact-timeout", "1"});
  RobotProcess gives_up(args, dir_.Join("robot2.log"));
  ASSERT_NO_FATAL_FAILURE(gives_up.Start());
  EXPECT_EQ(gives_up.Wait(), 1);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("robot2.log")),
              HasSubstr("nothing was observed or written"));
  EXPECT_FALSE(std::filesystem::exists(dir_.Join("r2") + "/queue"));
  ASSERT_NO_FATAL_FAILURE(StartServer());
  EXPECT_EQ(Stats("f-first", "r2").received(), 0u);
}

TEST_F(RobotIntegrationTest, TwoRobotsReplayEachOthersTracesAfterRefresh) {
  // Different stretches of the route, the same fleet, at the same time.
  std::vector<std::string> a =
      RobotArgs("f-share", "robot-a", kSummer, 600, 80.0, dir_.Join("a"));
  std::vector<std::string> b =
      RobotArgs("f-share", "robot-b", kSummer, 1600, 80.0, dir_.Join("b"));
  b.insert(b.end(), {"--first", "1000"});
  RobotProcess robot_a(a, dir_.Join("robot.log"));
  RobotProcess robot_b(b, dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(robot_a.Start());
  ASSERT_NO_FATAL_FAILURE(robot_b.Start());
  EXPECT_EQ(robot_a.Wait(), 0);
  EXPECT_EQ(robot_b.Wait(), 0);
  const robot::state::RobotStatus status_a = ReadStatus(dir_.Join("a"));
  const robot::state::RobotStatus status_b = ReadStatus(dir_.Join("b"));
  EXPECT_GT(status_a.counters().replayed_peer(), 0u);
  EXPECT_GT(status_b.counters().replayed_peer(), 0u);
  EXPECT_GT(status_a.dynamic_memory_by_robot().count("robot-b"), 0u);
  EXPECT_GT(status_b.dynamic_memory_by_robot().count("robot-a"), 0u);
  EXPECT_GT(status_a.counters().peer_clusters_added(), 0u);
}

// Issue 47: a summer robot uploads 400 places; a query-only winter robot
// relocalises over the same places with --sequence 10. Every scored query
// is scored twice (single frame and re-ranked over its sequence), the
// status file reports both, and over the sequence the recall is higher
// (HOG across seasons: SeqSLAM's case).
TEST_F(RobotIntegrationTest, AWinterRobotRelocalisesOverSequencesOfFrames) {
  RobotProcess summer(
      RobotArgs("f-seq", "summer-1", kSummer, 400, 0.0, dir_.Join("summer")),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(summer.Start());
  ASSERT_EQ(summer.Wait(), 0);
  EXPECT_EQ(Stats("f-seq", "summer-1").received(), 400u);
  std::vector<std::string> args =
      RobotArgs("f-seq", "winter-1", "nordland:" + kData + "/nordland/winter",
                400, 0.0, dir_.Join("winter"));
  args.insert(args.end(), {"--query-only", "--sequence", "10"});
  RobotProcess winter(args, dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(winter.Start());
  ASSERT_EQ(winter.Wait(), 0);
  const robot::state::RobotStatus status = ReadStatus(dir_.Join("winter"));
  const core::FirstCorrectRanks single =
      robot::RelocalisationRanks(status.counters());
  const core::FirstCorrectRanks sequence =
      robot::SequenceRanks(status.counters());
  EXPECT_EQ(single.size(), 400u);
  EXPECT_EQ(sequence.size(), single.size());
  EXPECT_DOUBLE_EQ(status.sequence_recall_at_1(), core::RecallAtK(sequence, 1));
  std::cout << "winter robot over 400 summer places: recall@1 "
            << core::RecallAtK(single, 1) << " single frames, "
            << core::RecallAtK(sequence, 1) << " over sequences of 10\n";
  EXPECT_GT(core::RecallAtK(sequence, 1), core::RecallAtK(single, 1));
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("robot.log")),
              HasSubstr("over sequences of 10 r@1"));
  // Issue 48: the first robot scored 0 against nothing but its own earlier
  // traces, and said nothing of why; now it is counted and said.
  const robot::state::RobotStatus first = ReadStatus(dir_.Join("summer"));
  EXPECT_GT(first.counters().relocalisation_own_only(), 0u);
  EXPECT_EQ(status.counters().relocalisation_own_only(), 0u);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("robot.log")),
              HasSubstr("answer was one of its own earlier traces"));
}

// Issue 47: a robot that joins with a learner a fleet holding two seasons
// fits its head on its first refresh before its first frame, and says so.
TEST_F(RobotIntegrationTest, ANewLearningRobotWarmStartsFromTwoSeasons) {
  for (const auto& [robot, source] :
       {std::pair<std::string, std::string>{"summer-1", kSummer},
        {"winter-1", "nordland:" + kData + "/nordland/winter"}}) {
    RobotProcess driver(
        RobotArgs("f-warm", robot, source, 200, 0.0, dir_.Join(robot)),
        dir_.Join("robot.log"));
    ASSERT_NO_FATAL_FAILURE(driver.Start());
    ASSERT_EQ(driver.Wait(), 0);
  }
  EXPECT_EQ(Stats("f-warm", "winter-1").received(), 200u);
  std::vector<std::string> args =
      RobotArgs("f-warm", "new-1", kSummer, 20, 0.0, dir_.Join("new-1"));
  args.insert(args.end(), {"--learn", "--query-only"});
  RobotProcess joining(args, dir_.Join("new.log"));
  ASSERT_NO_FATAL_FAILURE(joining.Start());
  ASSERT_EQ(joining.Wait(), 0);
  const std::string log = ReadFileOrEmpty(dir_.Join("new.log"));
  EXPECT_THAT(log, HasSubstr("warm start from the 400 traces of its first "
                             "refresh"));
  EXPECT_TRUE(std::filesystem::exists(dir_.Join("new-1/metric-head.bin")))
      << log;
}

TEST_F(RobotIntegrationTest, ARefusedUploadStopsTheRobotAndKeepsItsQueue) {
  // The fleet holds HOG codes; a robot with another encoder is refused
  // (FAILED_PRECONDITION / INVALID_ARGUMENT are not retried).
  RobotProcess first(
      RobotArgs("f-refuse", "r1", kSummer, 100, 0.0, dir_.Join("r1")),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(first.Start());
  ASSERT_EQ(first.Wait(), 0);
  std::vector<std::string> args =
      RobotArgs("f-refuse", "r2", kSummer, 2000, 200.0, dir_.Join("r2"));
  args.insert(args.end(), {"--encoder", "patchnorm-32x16-p8"});
  RobotProcess second(args, dir_.Join("robot2.log"));
  ASSERT_NO_FATAL_FAILURE(second.Start());
  EXPECT_EQ(second.Wait(), 1);
  const std::string log = ReadFileOrEmpty(dir_.Join("robot2.log"));
  EXPECT_THAT(log, HasSubstr("INVALID_ARGUMENT"));
  EXPECT_THAT(log, HasSubstr("the server refused traces seq 1.."));
  EXPECT_THAT(log, HasSubstr("stays in the queue"));
  const robot::state::RobotStatus status = ReadStatus(dir_.Join("r2"));
  EXPECT_EQ(status.phase(), "failed");
  EXPECT_EQ(status.queue_depth() + status.open_segment(),
            status.counters().observations());
  EXPECT_GT(status.queue_depth(), 0u);
  // It stopped observing at the refusal, not at the end of its source.
  EXPECT_LT(status.counters().observations(), 1000u);
  EXPECT_EQ(Stats("f-refuse", "r2").received(), 0u);
}

// A robot with the fleet's GPL model: learns every segment, uploads codes
// that carry the model's version, keeps its learned model and resumes it;
// a model of another version on the same data dir is refused up front.
TEST_F(RobotIntegrationTest, AGplRobotLearnsAndItsCodesCarryTheModelVersion) {
  auto model = robot::gpl::GplModel::Create({}, "gpl-it-v1");
  ASSERT_TRUE(model.ok()) << model.status();
  ASSERT_TRUE((*model)->Save(dir_.Join("fleet.pt")).ok());
  std::vector<std::string> args =
      RobotArgs("f-gpl", "g1", kSummer, 250, 0.0, dir_.Join("g1"));
  args.insert(args.end(), {"--gpl-model", dir_.Join("fleet.pt"), "--learn",
                           "--learn-steps", "5", "--torch-threads", "1"});
  RobotProcess robot(args, dir_.Join("gpl.log"));
  ASSERT_NO_FATAL_FAILURE(robot.Start());
  ASSERT_EQ(robot.Wait(), 0) << ReadFileOrEmpty(dir_.Join("gpl.log"));
  const v1::RobotStats stats = Stats("f-gpl", "g1");
  EXPECT_EQ(stats.received(), 250u);
  EXPECT_EQ(stats.max_seq(), 250u);
  std::unique_ptr<v1::MemoryService::Stub> stub = MakeStub(Address());
  Reply<v1::SampleReplayResponse> sample =
      SampleReplay(*stub, "f-gpl", "g1", 10);
  ASSERT_TRUE(sample.ok()) << Describe(sample.status);
  ASSERT_FALSE(sample.response.traces().empty());
  for (const v1::MemoryTrace& trace : sample.response.traces()) {
    EXPECT_EQ(trace.encoder_version(), "gpl-it-v1");
    EXPECT_EQ(trace.code_size(), 256);
    EXPECT_GE(trace.reward_external(), 0.0f);
  }
  auto learned =
      robot::gpl::GplModel::Load(dir_.Join("g1") + "/gpl-learned.pt");
  ASSERT_TRUE(learned.ok()) << learned.status();
  EXPECT_EQ((*learned)->version(), "gpl-it-v1");
  EXPECT_TRUE((*learned)->encoder_frozen());

  // Another fleet encoder on the same data dir: refused before observing.
  (*model)->set_version("gpl-it-v2");
  ASSERT_TRUE((*model)->Save(dir_.Join("fleet2.pt")).ok());
  std::vector<std::string> again =
      RobotArgs("f-gpl", "g1", kSummer, 300, 0.0, dir_.Join("g1"));
  again.insert(again.end(), {"--gpl-model", dir_.Join("fleet2.pt"), "--learn"});
  RobotProcess upgraded(again, dir_.Join("gpl2.log"));
  ASSERT_NO_FATAL_FAILURE(upgraded.Start());
  EXPECT_EQ(upgraded.Wait(), 2);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("gpl2.log")),
              HasSubstr("a new fleet encoder needs a new data dir"));
  EXPECT_EQ(Stats("f-gpl", "g1").received(), 250u);
}

// --learn without a GPL model: the metric head on the HOG fleet code. The
// robot learns every segment, uploads HOG codes and R_ex from its head,
// keeps the head in its data dir and resumes from it; a head that is not
// one is refused at start.
TEST_F(RobotIntegrationTest, ARobotLearnsAMetricHeadOnTheFleetCode) {
  std::vector<std::string> args =
      RobotArgs("f-metric", "m1", kSummer, 250, 0.0, dir_.Join("m1"));
  args.insert(args.end(), {"--learn"});
  RobotProcess robot(args, dir_.Join("metric.log"));
  ASSERT_NO_FATAL_FAILURE(robot.Start());
  ASSERT_EQ(robot.Wait(), 0) << ReadFileOrEmpty(dir_.Join("metric.log"));
  EXPECT_EQ(Stats("f-metric", "m1").received(), 250u);
  std::unique_ptr<v1::MemoryService::Stub> stub = MakeStub(Address());
  Reply<v1::SampleReplayResponse> sample =
      SampleReplay(*stub, "f-metric", "m1", 10);
  ASSERT_TRUE(sample.ok()) << Describe(sample.status);
  ASSERT_FALSE(sample.response.traces().empty());
  for (const v1::MemoryTrace& trace : sample.response.traces()) {
    EXPECT_EQ(trace.encoder_version(), "hog-64x32-c8-s8-b6-v1");
    EXPECT_GE(trace.reward_external(), 0.0f);
  }
  const std::string head = dir_.Join("m1") + "/metric-head.bin";
  auto loaded = robot::gpl::MetricHead::Deserialize(ReadFileOrEmpty(head), 504);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_TRUE(loaded->fitted());

  std::ofstream(head, std::ios::binary | std::ios::trunc) << "garbage";
  std::vector<std::string> again =
      RobotArgs("f-metric", "m1", kSummer, 300, 0.0, dir_.Join("m1"));
  again.push_back("--learn");
  RobotProcess corrupt(again, dir_.Join("metric2.log"));
  ASSERT_NO_FATAL_FAILURE(corrupt.Start());
  EXPECT_EQ(corrupt.Wait(), 2);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("metric2.log")),
              HasSubstr("the robot's learned head"));
  EXPECT_EQ(Stats("f-metric", "m1").received(), 250u);
}

// The robot's own traces of a fleet, by seq, as GetTraces finds them.
std::map<uint64_t, v1::MemoryTrace> TracesOf(v1::MemoryService::Stub& stub,
                                             const std::string& fleet,
                                             const std::string& robot,
                                             uint64_t last_seq) {
  v1::GetTracesRequest asked;
  asked.set_fleet_id(fleet);
  for (uint64_t seq = 1; seq <= last_seq; ++seq) {
    v1::TraceKey* key = asked.add_keys();
    key->set_robot_id(robot);
    key->set_seq(seq);
  }
  v1::GetTracesResponse got;
  const grpc::Status read = stub.GetTraces(MakeContext().get(), asked, &got);
  EXPECT_TRUE(read.ok()) << Describe(read);
  std::map<uint64_t, v1::MemoryTrace> by_seq;
  for (const v1::MemoryTrace& t : got.traces()) by_seq[t.seq()] = t;
  return by_seq;
}

// Issue 46's encoder migration, the robot's part: a robot that learned and
// re-scored on fleet mig-v1 (HOG codes) moves to mig-v2 (patch codes) with
// --migrate-from: what mig-v1 still holds of its traces arrives in mig-v2
// under the same seqs, re-encoded from its frames with R_ex kept; what an
// operator deleted from mig-v1 stays gone; the robot then goes on in
// mig-v2, also when killed once along the way; a further --migrate-from
// has nothing to do.
TEST_F(RobotIntegrationTest, ARobotMigratesItsTracesToANewEncodersFleet) {
  std::vector<std::string> args =
      RobotArgs("mig-v1", "m1", kSummer, 300, 0.0, dir_.Join("m1"));
  args.insert(args.end(), {"--learn", "--rescore"});
  RobotProcess first(args, dir_.Join("mig1.log"));
  ASSERT_NO_FATAL_FAILURE(first.Start());
  ASSERT_EQ(first.Wait(), 0) << ReadFileOrEmpty(dir_.Join("mig1.log"));
  // Re-scored after segments 2 and 3 (its segment-1 and -2 traces under the
  // head it had then); how many the fleet held at that moment depends on
  // the uploader's pace, so the request is what is checked.
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("mig1.log")),
              HasSubstr("remembered traces under the new head"));
  EXPECT_EQ(Stats("mig-v1", "m1").received(), 300u);

  std::unique_ptr<v1::MemoryService::Stub> stub = MakeStub(Address());
  v1::DeleteTracesRequest remove;
  remove.set_fleet_id("mig-v1");
  remove.set_robot_id("m1");
  remove.set_seq_first(1);
  remove.set_seq_last(20);
  v1::DeleteTracesResponse removed;
  grpc::Status status =
      stub->DeleteTraces(MakeContext().get(), remove, &removed);
  ASSERT_TRUE(status.ok()) << Describe(status);
  const std::map<uint64_t, v1::MemoryTrace> old =
      TracesOf(*stub, "mig-v1", "m1", 300);
  ASSERT_GT(old.size(), 200u);
  EXPECT_FALSE(old.contains(20));

  absl::StatusOr<std::unique_ptr<robot::ObservationSource>> source =
      robot::OpenSource(kSummer);
  ASSERT_TRUE(source.ok()) << source.status();
  absl::StatusOr<std::unique_ptr<robot::Encoder>> patch =
      robot::NewEncoderByName("patchnorm-32x16-p8");
  ASSERT_TRUE(patch.ok()) << patch.status();
  v1::CreateFleetRequest create;
  create.set_fleet_id("mig-v2");
  create.mutable_settings()->set_code_dimension(
      uint32_t((*patch)->dimension()));
  create.mutable_settings()->set_encoder_version((*patch)->version());
  v1::CreateFleetResponse made;
  status = stub->CreateFleet(MakeContext().get(), create, &made);
  ASSERT_TRUE(status.ok()) << Describe(status);

  std::vector<std::string> moved =
      RobotArgs("mig-v2", "m1", kSummer, 350, 0.0, dir_.Join("m1"));
  moved.insert(moved.end(), {"--migrate-from", "mig-v1", "--encoder",
                             "patchnorm-32x16-p8", "--learn"});
  // Killed once at a random moment after the migration began (in it, or
  // in the observing that follows), then run to the end: the same result.
  RobotProcess killed(moved, dir_.Join("mig2.log"));
  ASSERT_NO_FATAL_FAILURE(killed.Start());
  for (const auto give_up = Clock::now() + std::chrono::seconds(60);
       ReadFileOrEmpty(dir_.Join("mig2.log")).find("migrating from") ==
           std::string::npos &&
       Clock::now() < give_up;) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  std::mt19937 random(std::random_device{}());
  std::this_thread::sleep_for(std::chrono::milliseconds(
      std::uniform_int_distribution<int>(0, 400)(random)));
  killed.Kill();
  RobotProcess second(moved, dir_.Join("mig2.log"));
  ASSERT_NO_FATAL_FAILURE(second.Start());
  ASSERT_EQ(second.Wait(), 0) << ReadFileOrEmpty(dir_.Join("mig2.log"));
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("mig2.log")),
              HasSubstr(absl::StrCat("migrated to fleet mig-v2: ", old.size(),
                                     " traces re-encoded")));
  EXPECT_EQ(Stats("mig-v2", "m1").received(), old.size() + 50);
  const std::map<uint64_t, v1::MemoryTrace> now =
      TracesOf(*stub, "mig-v2", "m1", 350);
  for (const auto& [seq, before] : old) {
    ASSERT_TRUE(now.contains(seq)) << "seq " << seq;
    const v1::MemoryTrace& after = now.at(seq);
    EXPECT_EQ(after.encoder_version(), (*patch)->version());
    EXPECT_FLOAT_EQ(after.reward_external(), before.reward_external());
    EXPECT_EQ(after.pose().x(), before.pose().x());
    EXPECT_EQ(after.timestamp_ns(), before.timestamp_ns());
  }
  for (uint64_t seq = 1; seq <= 300; ++seq) {
    EXPECT_EQ(now.contains(seq), old.contains(seq)) << "seq " << seq;
  }
  for (uint64_t seq = 301; seq <= 350; ++seq) EXPECT_TRUE(now.contains(seq));
  // Seq 100 is observation 99 (the robot started at 0): its new code is
  // the patch code of that frame.
  absl::StatusOr<robot::Observation> frame = (*source)->Read(99);
  ASSERT_TRUE(frame.ok());
  absl::StatusOr<std::vector<float>> code = (*patch)->Encode(*frame);
  ASSERT_TRUE(code.ok());
  ASSERT_EQ(now.at(100).code_size(), int(code->size()));
  for (size_t c = 0; c < code->size(); ++c) {
    EXPECT_FLOAT_EQ(now.at(100).code(int(c)), (*code)[c]);
  }
  EXPECT_EQ(ReadStatus(dir_.Join("m1")).fleet_id(), "mig-v2");
  EXPECT_TRUE(
      std::filesystem::exists(dir_.Join("m1") + "/metric-head.bin.mig-v1.old"));

  RobotProcess third(moved, dir_.Join("mig3.log"));
  ASSERT_NO_FATAL_FAILURE(third.Start());
  ASSERT_EQ(third.Wait(), 0) << ReadFileOrEmpty(dir_.Join("mig3.log"));
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("mig3.log")),
              Not(HasSubstr("migrated to fleet")));
  EXPECT_EQ(Stats("mig-v2", "m1").received(), old.size() + 50);
}

TEST_F(RobotIntegrationTest, BadSourcesGiveAClearMessage) {
  struct Case {
    std::string source;
    std::string message;
  };
  const std::string truncated = dir_.Join("cut.clf.bz2");
  {
    const std::string bytes = ReadFileOrEmpty(kData + "/laser/aces.clf.bz2");
    std::ofstream(truncated, std::ios::binary)
        << bytes.substr(0, bytes.size() / 3);
  }
  const Case cases[] = {
      {"nordland:" + dir_.Join("missing"), "cannot list"},
      {"carmen:" + truncated, truncated + ": corrupt or truncated bzip2"},
      {"lidar:/x", "unknown source kind"},
  };
  for (const Case& c : cases) {
    RobotProcess robot(
        RobotArgs("f-bad", "r1", c.source, 10, 0.0, dir_.Join("bad")),
        dir_.Join("bad.log"));
    ASSERT_NO_FATAL_FAILURE(robot.Start());
    EXPECT_EQ(robot.Wait(), 1) << c.source;
    EXPECT_THAT(ReadFileOrEmpty(dir_.Join("bad.log")), HasSubstr(c.message));
  }
}

// A misspelt option in the robot's config file is a usage error (exit 2)
// naming it, not a silently kept default; a correct file is applied.
TEST_F(RobotIntegrationTest, AConfigFileWithAnUnknownOptionIsRefused) {
  const std::string source = "nordland:" + kData + "/nordland/summer";
  std::ofstream(dir_.Join("bad.toml")) << "upload-batchh = 10\n";
  std::vector<std::string> args =
      RobotArgs("f-config", "r1", source, 10, 0.0, dir_.Join("config"));
  args.insert(args.end(), {"--config", dir_.Join("bad.toml")});
  RobotProcess bad(args, dir_.Join("bad-config.log"));
  ASSERT_NO_FATAL_FAILURE(bad.Start());
  EXPECT_EQ(bad.Wait(), 2);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("bad-config.log")),
              HasSubstr("upload-batchh"));

  std::ofstream(dir_.Join("good.toml")) << "upload-batch = 3\n";
  args.back() = dir_.Join("good.toml");
  RobotProcess good(args, dir_.Join("good-config.log"));
  ASSERT_NO_FATAL_FAILURE(good.Start());
  EXPECT_EQ(good.Wait(), 0);
  EXPECT_EQ(Stats("f-config", "r1").received(), 10u);
}

TEST_F(RobotIntegrationTest, ACorruptImageStopsTheRobotAtItAndLosesNothing) {
  // Ten real frames, the sixth corrupt: the robot observes five, stops with
  // the file's name, and after the file is fixed resumes at the sixth.
  const std::string folder = dir_.Join("images");
  ASSERT_EQ(mkdir(folder.c_str(), 0755), 0);
  std::ofstream csv(folder + "/poses.csv");
  csv << "file,x,y\n";
  for (int i = 1; i <= 10; ++i) {
    const std::string name = absl::StrCat("images-", 10000 + i * 10, ".png");
    const std::string bytes =
        ReadFileOrEmpty(kData + "/nordland/summer/" + name);
    ASSERT_FALSE(bytes.empty()) << name;
    std::ofstream(folder + "/" + name, std::ios::binary)
        << (i == 6 ? bytes.substr(0, 60) : bytes);
    csv << name << "," << i * 10 << ",0\n";
  }
  csv.close();
  const std::string source =
      absl::StrCat("images:", folder, ",", folder, "/poses.csv");
  RobotProcess robot(
      RobotArgs("f-images", "r1", source, 10, 0.0, dir_.Join("r1")),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(robot.Start());
  EXPECT_EQ(robot.Wait(), 1);
  EXPECT_THAT(ReadFileOrEmpty(dir_.Join("robot.log")),
              HasSubstr("images-10060.png"));
  EXPECT_EQ(ReadStatus(dir_.Join("r1")).counters().next_index(), 5u);
  // Fix the file; the robot resumes at it.
  std::ofstream(folder + "/images-10060.png", std::ios::binary)
      << ReadFileOrEmpty(kData + "/nordland/summer/images-10060.png");
  RobotProcess again(
      RobotArgs("f-images", "r1", source, 10, 0.0, dir_.Join("r1")),
      dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(again.Start());
  EXPECT_EQ(again.Wait(), 0);
  const v1::RobotStats stats = Stats("f-images", "r1");
  EXPECT_EQ(stats.received(), 10u);
  EXPECT_EQ(stats.max_seq(), 10u);
}

TEST_F(RobotIntegrationTest, AFullRobotDiskStopsItCleanlyAndLosesNothing) {
  // The robot's data dir on a small tmpfs that another file fills up while
  // the robot observes: the next observation is refused by the disk reserve
  // with a clear error (exit 1, no abort, RocksDB never meets ENOSPC), what
  // was recorded before stays, and after space is freed a restart finishes
  // with every observation stored once.
  const std::string mount_point = dir_.Join("fs");
  ASSERT_EQ(mkdir(mount_point.c_str(), 0700), 0);
  SmallFilesystem filesystem(mount_point, 64);
  if (!filesystem.mounted()) GTEST_SKIP() << filesystem.why_not();
  const std::string data_dir = mount_point + "/robot";
  constexpr size_t kObservations = 2000;
  std::vector<std::string> args =
      RobotArgs("f-disk", "r1", kSummer, kObservations, 200.0, data_dir);
  args.insert(args.end(), {"--disk-reserve-mb", "16"});
  RobotProcess robot(args, dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(robot.Start());
  // Fill the disk once the robot records, not after a fixed delay.
  const auto deadline = Clock::now() + std::chrono::seconds(120);
  while (ReadStatus(data_dir).counters().next_index() == 0) {
    ASSERT_LT(Clock::now(), deadline) << "the robot never recorded";
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const std::string filler = mount_point + "/filler";
  Fill(filler, FreeBytes(mount_point) - 15 * kMiB);
  EXPECT_EQ(robot.Wait(), 1);
  const std::string log = ReadFileOrEmpty(dir_.Join("robot.log"));
  EXPECT_THAT(log, HasSubstr("disk nearly full"));
  const uint64_t recorded = ReadStatus(data_dir).counters().next_index();
  EXPECT_GT(recorded, 0u);
  EXPECT_LT(recorded, kObservations);
  // Free the space; the restarted robot goes on from where it stopped.
  ASSERT_EQ(unlink(filler.c_str()), 0);
  RobotProcess again(args, dir_.Join("robot.log"));
  ASSERT_NO_FATAL_FAILURE(again.Start());
  EXPECT_EQ(again.Wait(), 0);
  const v1::RobotStats stats = Stats("f-disk", "r1");
  EXPECT_EQ(stats.received(), kObservations);
  EXPECT_EQ(stats.max_seq(), kObservations);
  EXPECT_EQ(ReadStatus(data_dir).counters().observations(), kObservations);
}

}  // namespace
}  // namespace fleetmem::testing
