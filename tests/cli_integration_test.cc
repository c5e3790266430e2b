// End-to-end tests of the `fleetmem` command-line tool: the real binary runs
// as a child process (stdout and stderr captured, exit status checked)
// against a real fleetmem-server on a fresh RocksDB data directory. JSON
// output is parsed back into the fleetmem.v1 messages it claims to be.
#include <fcntl.h>
#include <poll.h>
#include <signal.h>
#include <spawn.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <chrono>
#include <cstring>
#include <fstream>
#include <iostream>
#include <memory>
#include <optional>
#include <set>
#include <sstream>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "fleetmem/v1/memory.pb.h"
#include "fleetmem_paths.h"
#include "google/protobuf/util/json_util.h"
#include "google/protobuf/util/message_differencer.h"
#include "gtest/gtest.h"
#include "tests/server_process.h"

extern char** environ;

namespace fleetmem::testing {
namespace {

using ::google::protobuf::util::MessageDifferencer;

constexpr char kFleet[] = "f";
constexpr int kRobots = 2;
constexpr int kPerRobot = 300;
constexpr int kTraces = kRobots * kPerRobot;
constexpr int kDim = 64;
// Bound of one run of the tool; a run that takes longer is killed and fails
// the test (it would otherwise hang the binary).
constexpr std::chrono::milliseconds kCliTimeout{20000};

std::string CliBinary() { return std::string(FLEETMEM_BIN_DIR) + "/fleetmem"; }

// What one run of the tool did.
struct CliRun {
  // Exit status; -signal if a signal ended it.
  int exit_code = -1;
  std::string out;
  std::string err;
  // The run exceeded its timeout and was killed.
  bool timed_out = false;
  // Why the tool could not be started or watched; empty when it could.
  std::string spawn_error;
  std::string command;

  // For failure messages.
  std::string Describe() const {
    return absl::StrCat("$ ", command, "\nexit ", exit_code,
                        timed_out ? " (timed out, killed)" : "", spawn_error,
                        "\n--- stdout ---\n", out, "--- stderr ---\n", err);
  }
};

// Runs `fleetmem args...` with stdin from /dev/null, captures stdout and
// stderr, and waits at most `timeout` (then SIGKILL). posix_spawn keeps the
// child safe in this multithreaded process (the server's reader thread).
CliRun RunFleetmem(const std::vector<std::string>& args,
                   std::chrono::milliseconds timeout = kCliTimeout) {
  CliRun run;
  std::vector<std::string> argv_strings = {CliBinary()};
  argv_strings.insert(argv_strings.end(), args.begin(), args.end());
  run.command = absl::StrJoin(argv_strings, " ");
  std::vector<char*> argv;
  for (std::string& arg : argv_strings) argv.push_back(arg.data());
  argv.push_back(nullptr);

  int out_pipe[2];
  int err_pipe[2];
  if (pipe2(out_pipe, O_CLOEXEC) != 0) {
    run.spawn_error = absl::StrCat(" pipe2: ", std::strerror(errno));
    return run;
  }
  if (pipe2(err_pipe, O_CLOEXEC) != 0) {
    run.spawn_error = absl::StrCat(" pipe2: ", std::strerror(errno));
    close(out_pipe[0]);
    close(out_pipe[1]);
    return run;
  }
  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, STDIN_FILENO, "/dev/null",
                                   O_RDONLY, 0);
  posix_spawn_file_actions_adddup2(&actions, out_pipe[1], STDOUT_FILENO);
  posix_spawn_file_actions_adddup2(&actions, err_pipe[1], STDERR_FILENO);
  pid_t pid = -1;
  const int spawned =
      posix_spawn(&pid, argv[0], &actions, nullptr, argv.data(), environ);
  posix_spawn_file_actions_destroy(&actions);
  close(out_pipe[1]);
  close(err_pipe[1]);
  if (spawned != 0) {
    run.spawn_error = absl::StrCat(" posix_spawn: ", std::strerror(spawned));
    close(out_pipe[0]);
    close(err_pipe[0]);
    return run;
  }

  const auto give_up = std::chrono::steady_clock::now() + timeout;
  struct Stream {
    int fd;
    std::string* text;
  };
  std::vector<Stream> open = {{out_pipe[0], &run.out}, {err_pipe[0], &run.err}};
  while (!open.empty()) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        give_up - std::chrono::steady_clock::now());
    if (left.count() <= 0) {
      run.timed_out = true;
      kill(pid, SIGKILL);
      break;
    }
    std::vector<pollfd> fds;
    for (const Stream& stream : open) fds.push_back({stream.fd, POLLIN, 0});
    const int ready =
        poll(fds.data(), fds.size(), static_cast<int>(left.count()));
    if (ready < 0 && errno != EINTR) {
      run.spawn_error = absl::StrCat(" poll: ", std::strerror(errno));
      kill(pid, SIGKILL);
      break;
    }
    for (size_t i = fds.size(); i-- > 0;) {
      if (fds[i].revents == 0) continue;
      char buffer[4096];
      const ssize_t n = read(open[i].fd, buffer, sizeof(buffer));
      if (n > 0) {
        open[i].text->append(buffer, static_cast<size_t>(n));
      } else if (n == 0 || errno != EINTR) {
        close(open[i].fd);
        open.erase(open.begin() + static_cast<std::ptrdiff_t>(i));
      }
    }
  }
  for (const Stream& stream : open) close(stream.fd);
  int status = 0;
  while (waitpid(pid, &status, 0) < 0 && errno == EINTR) {
  }
  if (WIFEXITED(status)) run.exit_code = WEXITSTATUS(status);
  if (WIFSIGNALED(status)) run.exit_code = -WTERMSIG(status);
  return run;
}

// Parses protobuf JSON printed by the tool (one message, one line).
template <typename Message>
::testing::AssertionResult ParseJson(absl::string_view text, Message* message) {
  const auto status = google::protobuf::util::JsonStringToMessage(
      std::string(absl::StripAsciiWhitespace(text)), message);
  if (!status.ok()) {
    return ::testing::AssertionFailure() << "not a " << message->GetTypeName()
                                         << ": " << status.ToString() << "\n"
                                         << text;
  }
  return ::testing::AssertionSuccess();
}

// The non-empty lines of `text`.
std::vector<std::string> Lines(absl::string_view text) {
  return absl::StrSplit(text, '\n', absl::SkipEmpty());
}

// The value of row `label` of a two-column table printed by the tool (the
// label column is padded with at least two spaces), if there is such a row.
std::optional<std::string> TableValue(absl::string_view table,
                                      absl::string_view label) {
  for (const std::string& line : Lines(table)) {
    if (absl::StartsWith(line, absl::StrCat(label, "  "))) {
      return std::string(absl::StripAsciiWhitespace(
          absl::string_view(line).substr(label.size())));
    }
  }
  return std::nullopt;
}

// The line of a traces file (JSON Lines) holding (robot, seq), or "".
std::string FindTraceLine(const std::string& path, const std::string& robot,
                          uint64_t seq) {
  std::ifstream in(path);
  std::string line;
  while (std::getline(in, line)) {
    v1::MemoryTrace trace;
    if (!google::protobuf::util::JsonStringToMessage(line, &trace).ok()) {
      continue;
    }
    if (trace.robot_id() == robot && trace.seq() == seq) return line;
  }
  return "";
}

void WriteFile(const std::string& path, const std::string& contents) {
  std::ofstream out(path, std::ios::binary | std::ios::trunc);
  out << contents;
  ASSERT_TRUE(out.good()) << "cannot write " << path;
}

// Help needs no server.
TEST(CliHelpTest, HelpListsEveryCommand) {
  const CliRun run = RunFleetmem({"help"});
  ASSERT_EQ(run.exit_code, 0) << run.Describe();
  EXPECT_TRUE(absl::StrContains(run.out, "Usage: fleetmem")) << run.Describe();
  for (const char* command : {"gen-traces", "upload", "consolidate", "stats",
                              "sample", "query", "watch"}) {
    EXPECT_TRUE(absl::StrContains(run.out, absl::StrCat("  ", command, " ")))
        << command << "\n"
        << run.Describe();
  }
}

TEST(CliHelpTest, CommandHelpShowsItsUsage) {
  for (const char* command : {"gen-traces", "upload", "consolidate", "stats",
                              "sample", "query", "watch"}) {
    const std::string usage = absl::StrCat("Usage: fleetmem ", command, " ");
    const CliRun flag_help = RunFleetmem({command, "--help"});
    EXPECT_EQ(flag_help.exit_code, 0) << flag_help.Describe();
    EXPECT_TRUE(absl::StrContains(flag_help.out, "\n" + usage))
        << flag_help.Describe();
    EXPECT_TRUE(flag_help.err.empty()) << flag_help.Describe();

    const CliRun help_command = RunFleetmem({"help", command});
    EXPECT_EQ(help_command.exit_code, 0) << help_command.Describe();
    EXPECT_EQ(help_command.out, flag_help.out);
  }
}

TEST(CliHelpTest, UnknownCommandIsAUsageError) {
  const CliRun run = RunFleetmem({"frobnicate"});
  EXPECT_EQ(run.exit_code, 2) << run.Describe();
  EXPECT_TRUE(absl::StrContains(run.err, "unknown command 'frobnicate'"))
      << run.Describe();
  EXPECT_TRUE(run.out.empty()) << run.Describe();

  const CliRun help = RunFleetmem({"help", "frobnicate"});
  EXPECT_EQ(help.exit_code, 2) << help.Describe();

  const CliRun none = RunFleetmem({});
  EXPECT_EQ(none.exit_code, 2) << none.Describe();
}

// A fresh server per test; tests talk to it only through the tool.
class CliTest : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_FALSE(dir_.path().empty());
    const std::string data_dir = dir_.Join("data");
    ASSERT_EQ(mkdir(data_dir.c_str(), 0755), 0) << std::strerror(errno);
    ServerOptions options;
    options.data_dir = data_dir;
    options.log_file = dir_.Join("server.log");
    if (const std::string config = ServerConfig(); !config.empty()) {
      options.config_file = dir_.Join("server.textproto");
      ASSERT_NO_FATAL_FAILURE(WriteFile(options.config_file, config));
    }
    server_ = std::make_unique<ServerProcess>(options);
    const absl::Status started = server_->Start();
    ASSERT_TRUE(started.ok()) << started;
    traces_file_ = dir_.Join("traces.jsonl");
  }

  void TearDown() override {
    if (server_ != nullptr && server_->running()) {
      const absl::StatusOr<int> code = server_->Stop();
      EXPECT_TRUE(code.ok() && *code == 0)
          << "server did not stop cleanly: "
          << (code.ok() ? absl::StrCat("exit ", *code)
                        : code.status().ToString());
    }
    if (HasFailure() && server_ != nullptr) {
      std::cerr << "--- server output ---\n" << server_->Output();
    }
  }

  // The server's --config file's text (none if empty).
  virtual std::string ServerConfig() const { return ""; }

  // `fleetmem --server ADDRESS args...`.
  CliRun Fleetmem(std::vector<std::string> args,
                  std::chrono::milliseconds timeout = kCliTimeout) {
    args.insert(args.begin(), {"--server", server_->address()});
    return RunFleetmem(args, timeout);
  }

  // gen-traces of kRobots x kPerRobot traces of dimension kDim into
  // traces_file_.
  void GenerateTraces() {
    const CliRun run =
        RunFleetmem({"gen-traces", "--robots", absl::StrCat(kRobots),
                     "--per-robot", absl::StrCat(kPerRobot), "--dim",
                     absl::StrCat(kDim), "--out", traces_file_});
    ASSERT_EQ(run.exit_code, 0) << run.Describe();
    EXPECT_TRUE(run.out.empty()) << run.Describe();
    EXPECT_TRUE(absl::StrContains(run.err, absl::StrCat("wrote ", kTraces)))
        << run.Describe();
  }

  // Generates the traces and uploads them; expects all accepted.
  void GenerateAndUpload() {
    ASSERT_NO_FATAL_FAILURE(GenerateTraces());
    const CliRun upload =
        Fleetmem({"upload", "--fleet", kFleet, "--file", traces_file_});
    ASSERT_EQ(upload.exit_code, 0) << upload.Describe();
    ASSERT_EQ(TableValue(upload.out, "accepted"), absl::StrCat(kTraces))
        << upload.Describe();
  }

  // GenerateAndUpload, then `--json consolidate`.
  void Populate() {
    ASSERT_NO_FATAL_FAILURE(GenerateAndUpload());
    const CliRun run = Fleetmem({"--json", "consolidate", "--fleet", kFleet});
    ASSERT_EQ(run.exit_code, 0) << run.Describe();
    v1::ConsolidateResponse response;
    ASSERT_TRUE(ParseJson(run.out, &response));
    consolidated_ = response;
  }

  // `--json stats --fleet FLEET`, parsed.
  void Stats(v1::GetStatsResponse* stats, const std::string& fleet = kFleet) {
    const CliRun run = Fleetmem({"--json", "stats", "--fleet", fleet});
    ASSERT_EQ(run.exit_code, 0) << run.Describe();
    ASSERT_TRUE(ParseJson(run.out, stats));
  }

  TempDir dir_{"fleetmem-cli-it-"};
  std::unique_ptr<ServerProcess> server_;
  std::string traces_file_;
  v1::ConsolidateResponse consolidated_;
};

TEST_F(CliTest, GenTracesWritesTheRequestedTraces) {
  ASSERT_NO_FATAL_FAILURE(GenerateTraces());
  const std::string text = ReadFileOrEmpty(traces_file_);
  const std::vector<std::string> lines = Lines(text);
  ASSERT_EQ(lines.size(), static_cast<size_t>(kTraces));
  std::set<std::pair<std::string, uint64_t>> ids;
  for (const std::string& line : lines) {
    v1::MemoryTrace trace;
    ASSERT_TRUE(ParseJson(line, &trace));
    EXPECT_EQ(trace.code_size(), kDim) << line;
    EXPECT_EQ(trace.encoder_version(), "v1") << line;
    EXPECT_GE(trace.seq(), 1u);
    EXPECT_LE(trace.seq(), static_cast<uint64_t>(kPerRobot));
    ids.emplace(trace.robot_id(), trace.seq());
  }
  EXPECT_EQ(ids.size(), static_cast<size_t>(kTraces));
  EXPECT_TRUE(ids.count({"robot-1", 1}) == 1 &&
              ids.count({"robot-2", 300}) == 1);

  // Same seed, same output.
  const std::string again = dir_.Join("again.jsonl");
  const CliRun run = RunFleetmem(
      {"gen-traces", "--robots", absl::StrCat(kRobots), "--per-robot",
       absl::StrCat(kPerRobot), "--dim", absl::StrCat(kDim), "--out", again});
  ASSERT_EQ(run.exit_code, 0) << run.Describe();
  EXPECT_TRUE(ReadFileOrEmpty(again) == text)
      << "gen-traces is not deterministic";
}

TEST_F(CliTest, UploadTwiceStoresOnce) {
  ASSERT_NO_FATAL_FAILURE(GenerateTraces());
  const CliRun first =
      Fleetmem({"upload", "--fleet", kFleet, "--file", traces_file_});
  ASSERT_EQ(first.exit_code, 0) << first.Describe();
  EXPECT_EQ(TableValue(first.out, "accepted"), absl::StrCat(kTraces))
      << first.Describe();
  EXPECT_EQ(TableValue(first.out, "duplicates"), "0") << first.Describe();

  const CliRun second =
      Fleetmem({"upload", "--fleet", kFleet, "--file", traces_file_});
  ASSERT_EQ(second.exit_code, 0) << second.Describe();
  EXPECT_EQ(TableValue(second.out, "accepted"), "0") << second.Describe();
  EXPECT_EQ(TableValue(second.out, "duplicates"), absl::StrCat(kTraces))
      << second.Describe();
  EXPECT_EQ(TableValue(second.out, "consolidations"), "0") << second.Describe();

  v1::GetStatsResponse stats;
  ASSERT_NO_FATAL_FAILURE(Stats(&stats));
  ASSERT_EQ(stats.robots_size(), kRobots) << stats.DebugString();
  for (const v1::RobotStats& robot : stats.robots()) {
    EXPECT_EQ(robot.received(), static_cast<uint64_t>(kPerRobot))
        << robot.DebugString();
  }
}

TEST_F(CliTest, ConsolidateThenStats) {
  ASSERT_NO_FATAL_FAILURE(Populate());
  v1::GetStatsResponse stats;
  ASSERT_NO_FATAL_FAILURE(Stats(&stats));

  EXPECT_EQ(stats.pending_traces(), 0u) << stats.DebugString();
  EXPECT_GT(stats.traces(), 0u);
  EXPECT_LE(stats.traces() + stats.pending_traces(),
            static_cast<uint64_t>(kTraces));
  EXPECT_EQ(stats.traces(), consolidated_.traces());
  EXPECT_EQ(stats.clusters(), consolidated_.clusters());
  EXPECT_GT(stats.clusters(), 0u);
  EXPECT_LE(stats.clusters(), 100u);
  EXPECT_LE(stats.clusters(), stats.max_clusters());
  EXPECT_LE(stats.traces(), stats.clusters() * stats.max_traces_per_cluster());
  EXPECT_EQ(stats.code_dimension(), static_cast<uint32_t>(kDim));
  EXPECT_EQ(stats.encoder_version(), "v1");
  EXPECT_GE(stats.consolidations(), 1u);

  ASSERT_EQ(stats.robots_size(), kRobots) << stats.DebugString();
  std::set<std::string> robots;
  uint64_t robot_traces = 0;
  uint64_t robot_pending = 0;
  for (const v1::RobotStats& robot : stats.robots()) {
    robots.insert(robot.robot_id());
    robot_traces += robot.traces();
    robot_pending += robot.pending_traces();
    EXPECT_EQ(robot.received(), static_cast<uint64_t>(kPerRobot));
    EXPECT_EQ(robot.max_seq(), static_cast<uint64_t>(kPerRobot));
  }
  EXPECT_EQ(robots, (std::set<std::string>{"robot-1", "robot-2"}));
  EXPECT_EQ(robot_traces, stats.traces());
  EXPECT_EQ(robot_pending, stats.pending_traces());
  uint64_t domain_traces = 0;
  for (const v1::DomainStats& domain : stats.domains()) {
    domain_traces += domain.traces() + domain.pending_traces();
  }
  EXPECT_EQ(domain_traces, stats.traces() + stats.pending_traces());

  // Nothing is left to consolidate.
  const CliRun again = Fleetmem({"consolidate", "--fleet", kFleet});
  ASSERT_EQ(again.exit_code, 0) << again.Describe();
  EXPECT_EQ(TableValue(again.out, "consolidated traces"), "0")
      << again.Describe();
  EXPECT_EQ(TableValue(again.out, "traces"), absl::StrCat(stats.traces()))
      << again.Describe();
}

TEST_F(CliTest, SampleGivesDistinctReplayedTraces) {
  ASSERT_NO_FATAL_FAILURE(Populate());
  const CliRun run = Fleetmem({"--json", "sample", "--fleet", kFleet, "--robot",
                               "robot-1", "--count", "5"});
  ASSERT_EQ(run.exit_code, 0) << run.Describe();
  v1::SampleReplayResponse response;
  ASSERT_TRUE(ParseJson(run.out, &response));
  ASSERT_EQ(response.traces_size(), 5) << run.Describe();
  std::set<std::pair<std::string, uint64_t>> ids;
  for (const v1::MemoryTrace& trace : response.traces()) {
    ids.emplace(trace.robot_id(), trace.seq());
    EXPECT_GE(trace.replay_count(), 1u) << trace.ShortDebugString();
    EXPECT_NE(trace.cluster_id(), 0u) << trace.ShortDebugString();
    EXPECT_EQ(trace.code_size(), kDim);
  }
  EXPECT_EQ(ids.size(), 5u) << run.Describe();

  v1::GetStatsResponse stats;
  ASSERT_NO_FATAL_FAILURE(Stats(&stats));
  for (const v1::RobotStats& robot : stats.robots()) {
    EXPECT_EQ(robot.replayed(), robot.robot_id() == "robot-1" ? 5u : 0u)
        << robot.DebugString();
  }
}

TEST_F(CliTest, QueryWithAStoredCodeFindsThatTraceFirst) {
  ASSERT_NO_FATAL_FAILURE(Populate());
  // A trace that the memory holds (consolidation may downsample some).
  const CliRun sample = Fleetmem({"--json", "sample", "--fleet", kFleet,
                                  "--robot", "robot-2", "--count", "1"});
  ASSERT_EQ(sample.exit_code, 0) << sample.Describe();
  v1::SampleReplayResponse sampled;
  ASSERT_TRUE(ParseJson(sample.out, &sampled));
  ASSERT_EQ(sampled.traces_size(), 1);
  const v1::MemoryTrace& stored = sampled.traces(0);

  // Its line of the generated file is the query.
  const std::string line =
      FindTraceLine(traces_file_, stored.robot_id(), stored.seq());
  ASSERT_FALSE(line.empty()) << stored.ShortDebugString();
  const std::string code_file = dir_.Join("code.json");
  ASSERT_NO_FATAL_FAILURE(WriteFile(code_file, line + "\n"));

  const CliRun run = Fleetmem({"--json", "query", "--fleet", kFleet,
                               "--code-file", code_file, "--k", "3"});
  ASSERT_EQ(run.exit_code, 0) << run.Describe();
  v1::QueryPlaceResponse response;
  ASSERT_TRUE(ParseJson(run.out, &response));
  ASSERT_EQ(response.matches_size(), 3) << run.Describe();
  const v1::PlaceMatch& best = response.matches(0);
  EXPECT_EQ(best.trace().robot_id(), stored.robot_id()) << run.Describe();
  EXPECT_EQ(best.trace().seq(), stored.seq()) << run.Describe();
  EXPECT_NEAR(best.distance(), 0.0, 1e-4) << run.Describe();
  EXPECT_GT(response.matches(1).distance(), 1e-3) << run.Describe();
  EXPECT_LE(response.matches(1).distance(), response.matches(2).distance());

  // The table form ranks the same trace first.
  const CliRun table = Fleetmem(
      {"query", "--fleet", kFleet, "--code-file", code_file, "--k", "1"});
  ASSERT_EQ(table.exit_code, 0) << table.Describe();
  const std::vector<std::string> rows = Lines(table.out);
  ASSERT_EQ(rows.size(), 2u) << table.Describe();
  const std::vector<std::string> cells =
      absl::StrSplit(rows[1], ' ', absl::SkipEmpty());
  ASSERT_GE(cells.size(), 4u) << table.Describe();
  EXPECT_EQ(cells[0], "1");
  EXPECT_EQ(cells[2], stored.robot_id());
  EXPECT_EQ(cells[3], absl::StrCat(stored.seq()));
}

// A server whose fleets get a graph from 100 codes on (the default is
// 20,000): the import's graph is built from this test's few hundred.
class CliImportTest : public CliTest {
 protected:
  std::string ServerConfig() const override {
    return "hnsw { hnsw_from: 100 }\n";
  }

  // `--json import --fleet FLEET --from DIR args...`, parsed.
  void Import(const std::string& fleet, const std::string& dir,
              std::vector<std::string> args,
              v1::ImportTracesResponse* response) {
    args.insert(args.begin(),
                {"--json", "import", "--fleet", fleet, "--from", dir});
    const CliRun run = Fleetmem(args);
    ASSERT_EQ(run.exit_code, 0) << run.Describe();
    ASSERT_TRUE(ParseJson(run.out, response)) << run.Describe();
  }
};

// A fleet's export imported into a new fleet, 64 rows a call: every row
// accepted, the graph built by the last call (no code left outside it),
// the imported traces found by their codes; a second import is refused
// and changes nothing, and one with --resume finds every row there.
TEST_F(CliImportTest, AnExportImportsIntoANewFleetWithItsGraphBuiltAtTheEnd) {
  ASSERT_NO_FATAL_FAILURE(Populate());
  const std::string exported = dir_.Join("export");
  const CliRun exporting =
      Fleetmem({"export", "--fleet", kFleet, "--out", exported});
  ASSERT_EQ(exporting.exit_code, 0) << exporting.Describe();
  v1::GetStatsResponse original;
  ASSERT_NO_FATAL_FAILURE(Stats(&original));
  const uint64_t rows = original.traces() + original.pending_traces();
  ASSERT_GT(rows, 100u);

  v1::ImportTracesResponse imported;
  ASSERT_NO_FATAL_FAILURE(
      Import("copy", exported, {"--chunk", "64"}, &imported));
  EXPECT_EQ(imported.accepted(), rows);
  EXPECT_EQ(imported.duplicates(), 0u);
  EXPECT_EQ(imported.unindexed_codes(), 0u);
  v1::GetStatsResponse copy;
  ASSERT_NO_FATAL_FAILURE(Stats(&copy, "copy"));
  EXPECT_EQ(copy.unindexed_codes(), 0u) << copy.DebugString();
  EXPECT_EQ(copy.traces() + copy.pending_traces(), imported.fleet_traces());
  EXPECT_GT(copy.traces(), 0u) << "consolidated as uploads are";
  EXPECT_EQ(copy.code_dimension(), static_cast<uint32_t>(kDim));
  uint64_t received = 0;
  for (const v1::RobotStats& robot : copy.robots()) {
    received += robot.received();
  }
  EXPECT_EQ(received, rows);

  // A trace the copy holds is found first by its code (from the generated
  // file the original fleet was uploaded from).
  const CliRun sample = Fleetmem({"--json", "sample", "--fleet", "copy",
                                  "--robot", "robot-1", "--count", "1"});
  ASSERT_EQ(sample.exit_code, 0) << sample.Describe();
  v1::SampleReplayResponse sampled;
  ASSERT_TRUE(ParseJson(sample.out, &sampled));
  ASSERT_EQ(sampled.traces_size(), 1);
  const v1::MemoryTrace& stored = sampled.traces(0);
  const std::string code_file = dir_.Join("code.json");
  ASSERT_NO_FATAL_FAILURE(WriteFile(
      code_file,
      FindTraceLine(traces_file_, stored.robot_id(), stored.seq()) + "\n"));
  const CliRun query = Fleetmem({"--json", "query", "--fleet", "copy",
                                 "--code-file", code_file, "--k", "1"});
  ASSERT_EQ(query.exit_code, 0) << query.Describe();
  v1::QueryPlaceResponse found;
  ASSERT_TRUE(ParseJson(query.out, &found));
  ASSERT_EQ(found.matches_size(), 1);
  EXPECT_EQ(found.matches(0).trace().seq(), stored.seq());
  EXPECT_NEAR(found.matches(0).distance(), 0.0, 1e-4);

  const CliRun again =
      Fleetmem({"import", "--fleet", "copy", "--from", exported});
  EXPECT_EQ(again.exit_code, 1) << again.Describe();
  EXPECT_TRUE(absl::StrContains(again.err, "FAILED_PRECONDITION"))
      << again.Describe();
  EXPECT_TRUE(absl::StrContains(again.err, "nothing was imported"))
      << again.Describe();
  v1::GetStatsResponse unchanged;
  ASSERT_NO_FATAL_FAILURE(Stats(&unchanged, "copy"));
  EXPECT_EQ(unchanged.traces() + unchanged.pending_traces(),
            imported.fleet_traces());

  v1::ImportTracesResponse resumed;
  ASSERT_NO_FATAL_FAILURE(Import("copy", exported, {"--resume"}, &resumed));
  EXPECT_EQ(resumed.accepted(), 0u);
  EXPECT_EQ(resumed.duplicates(), rows);
}

// Arrays that do not fit each other, or no rewards, are usage errors
// naming the file: nothing is sent, no fleet is made.
TEST_F(CliTest, ImportRefusesArraysThatDoNotFitAndMakesNoFleet) {
  const std::string dir = dir_.Join("arrays");
  ASSERT_EQ(mkdir(dir.c_str(), 0755), 0) << std::strerror(errno);
  // NumPy 1.0 files of float32 / float64 rows (64-byte aligned headers).
  const auto npy = [&](const std::string& name, const char* descr, int rows,
                       int cols, size_t width) {
    std::string dict = absl::StrCat("{'descr': '", descr,
                                    "', 'fortran_order': False, 'shape': (",
                                    rows, ", ", cols, "), }");
    dict.append((64 - (10 + dict.size() + 1) % 64) % 64, ' ');
    dict.push_back('\n');
    std::string bytes("\x93NUMPY\x01\x00", 8);
    bytes.push_back(static_cast<char>(dict.size()));
    bytes.push_back('\0');
    WriteFile(dir + "/" + name,
              bytes + dict + std::string(rows * cols * width, '\0'));
  };
  npy("codes.npy", "<f4", 3, 8, 4);
  npy("places.npy", "<f8", 2, 4, 8);
  CliRun run = Fleetmem({"import", "--fleet", "bad", "--from", dir});
  EXPECT_EQ(run.exit_code, 2) << run.Describe();
  EXPECT_TRUE(absl::StrContains(run.err, "places.npy is 2 x 4; want 3 rows"))
      << run.Describe();
  npy("places.npy", "<f8", 3, 2, 8);
  run = Fleetmem({"import", "--fleet", "bad", "--from", dir});
  EXPECT_EQ(run.exit_code, 2) << run.Describe();
  EXPECT_TRUE(absl::StrContains(run.err, "neither metadata.csv"))
      << run.Describe();
  const CliRun fleets = Fleetmem({"fleets"});
  ASSERT_EQ(fleets.exit_code, 0) << fleets.Describe();
  EXPECT_FALSE(absl::StrContains(fleets.out, "bad")) << fleets.Describe();
}

TEST_F(CliTest, WatchPrintsEventsFromTheCursor) {
  ASSERT_NO_FATAL_FAILURE(Populate());
  v1::GetStatsResponse stats;
  ASSERT_NO_FATAL_FAILURE(Stats(&stats));
  ASSERT_GE(stats.last_event_id(), 5u) << stats.DebugString();

  const CliRun first =
      Fleetmem({"watch", "--fleet", kFleet, "--max-events", "3"});
  ASSERT_EQ(first.exit_code, 0) << first.Describe();
  const std::vector<std::string> lines = Lines(first.out);
  ASSERT_EQ(lines.size(), 3u) << first.Describe();
  for (size_t i = 0; i < lines.size(); ++i) {
    EXPECT_TRUE(
        absl::StartsWith(lines[i], absl::StrCat(i + 1, " CLUSTER_ADDED ")))
        << first.Describe();
  }
  EXPECT_TRUE(absl::StrContains(first.err, "last event id: 3"))
      << first.Describe();

  const CliRun resumed = Fleetmem({"--json", "watch", "--fleet", kFleet,
                                   "--after", "3", "--max-events", "2"});
  ASSERT_EQ(resumed.exit_code, 0) << resumed.Describe();
  const std::vector<std::string> events = Lines(resumed.out);
  ASSERT_EQ(events.size(), 2u) << resumed.Describe();
  for (size_t i = 0; i < events.size(); ++i) {
    v1::MemoryEvent event;
    ASSERT_TRUE(ParseJson(events[i], &event));
    EXPECT_EQ(event.id(), 4 + i) << resumed.Describe();
    EXPECT_EQ(event.type(), v1::MemoryEvent::CLUSTER_ADDED);
    EXPECT_GT(event.trace_count(), 0u);
  }
  EXPECT_TRUE(absl::StrContains(resumed.err, "last event id: 5"))
      << resumed.Describe();
}

TEST_F(CliTest, BadInputIsReportedAndChangesNothing) {
  ASSERT_NO_FATAL_FAILURE(GenerateAndUpload());
  v1::GetStatsResponse before;
  ASSERT_NO_FATAL_FAILURE(Stats(&before));

  const CliRun bad_id = Fleetmem({"stats", "--fleet", "bad/id"});
  EXPECT_EQ(bad_id.exit_code, 1) << bad_id.Describe();
  EXPECT_TRUE(absl::StartsWith(bad_id.err, "error: INVALID_ARGUMENT"))
      << bad_id.Describe();
  EXPECT_TRUE(bad_id.out.empty()) << bad_id.Describe();

  const CliRun missing = Fleetmem({"stats", "--fleet", "nope"});
  EXPECT_EQ(missing.exit_code, 1) << missing.Describe();
  EXPECT_TRUE(absl::StartsWith(missing.err, "error: NOT_FOUND"))
      << missing.Describe();

  // A new good trace and one of the wrong dimension in one upload: the
  // message is refused as a whole.
  v1::MemoryTrace good;
  ASSERT_TRUE(ParseJson(FindTraceLine(traces_file_, "robot-1", 1), &good));
  good.set_robot_id("robot-3");
  v1::MemoryTrace wrong = good;
  wrong.set_seq(2);
  wrong.mutable_code()->Truncate(kDim / 2);
  std::string file_text;
  for (const v1::MemoryTrace* trace : {&good, &wrong}) {
    std::string json;
    ASSERT_TRUE(
        google::protobuf::util::MessageToJsonString(*trace, &json).ok());
    absl::StrAppend(&file_text, json, "\n");
  }
  const std::string bad_file = dir_.Join("wrong-dimension.jsonl");
  ASSERT_NO_FATAL_FAILURE(WriteFile(bad_file, file_text));
  const CliRun wrong_dim =
      Fleetmem({"upload", "--fleet", kFleet, "--file", bad_file});
  EXPECT_EQ(wrong_dim.exit_code, 1) << wrong_dim.Describe();
  EXPECT_TRUE(absl::StartsWith(wrong_dim.err, "error: INVALID_ARGUMENT"))
      << wrong_dim.Describe();

  v1::GetStatsResponse after;
  ASSERT_NO_FATAL_FAILURE(Stats(&after));
  EXPECT_TRUE(MessageDifferencer::Equals(before, after))
      << "before:\n"
      << before.DebugString() << "after:\n"
      << after.DebugString();

  const CliRun no_file = Fleetmem({"upload", "--fleet", kFleet});
  EXPECT_EQ(no_file.exit_code, 2) << no_file.Describe();
  EXPECT_TRUE(absl::StrContains(no_file.err, "--file is required"))
      << no_file.Describe();

  // A file that is not JSON Lines of traces is the user's error, not the
  // server's.
  const std::string garbage = dir_.Join("garbage.jsonl");
  ASSERT_NO_FATAL_FAILURE(WriteFile(garbage, "{\"robotId\": \n"));
  const CliRun unparsable =
      Fleetmem({"upload", "--fleet", kFleet, "--file", garbage});
  EXPECT_EQ(unparsable.exit_code, 2) << unparsable.Describe();
  EXPECT_TRUE(absl::StrContains(unparsable.err, "line 1"))
      << unparsable.Describe();
}

// `fleetmem health` is the probe of the images and of Kubernetes: exit 0
// only for SERVING.
TEST_F(CliTest, HealthIsServingAndAnUnknownServiceIsAnError) {
  const std::string address = server_->address();
  CliRun run = RunFleetmem({"--server", address, "health"});
  EXPECT_EQ(run.exit_code, 0) << run.Describe();
  EXPECT_EQ(run.out, "SERVING\n") << run.Describe();

  run = RunFleetmem({"--server", address, "health", "--service", "nope.v1"});
  EXPECT_EQ(run.exit_code, 1) << run.Describe();
  EXPECT_TRUE(absl::StartsWith(run.err, "error: NOT_FOUND")) << run.Describe();
}

TEST_F(CliTest, StoppedServerIsAServerErrorWithoutHanging) {
  const std::string address = server_->address();
  const absl::StatusOr<int> stopped = server_->Stop();
  ASSERT_TRUE(stopped.ok()) << stopped.status();
  EXPECT_EQ(*stopped, 0);

  for (const char* command : {"stats", "health"}) {
    std::vector<std::string> args = {"--server", address, "--deadline-ms",
                                     "300", command};
    if (std::string(command) == "stats") {
      args.insert(args.end(), {"--fleet", kFleet});
    }
    const CliRun run = RunFleetmem(args);
    EXPECT_FALSE(run.timed_out) << run.Describe();
    EXPECT_EQ(run.exit_code, 1) << run.Describe();
    EXPECT_TRUE(absl::StartsWith(run.err, "error: UNAVAILABLE") ||
                absl::StartsWith(run.err, "error: DEADLINE_EXCEEDED"))
        << run.Describe();
    EXPECT_TRUE(run.out.empty()) << run.Describe();
  }
}

}  // namespace
}  // namespace fleetmem::testing
