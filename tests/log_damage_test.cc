// One flipped byte in the ingest log of a killed server (the third outside
// sweep: a damaged record in the middle of the newest segment was read as
// a torn tail, and every acknowledged entry after it, 24,600 traces, was
// dropped without a word). Each trial: a robot uploads at full speed
// (acknowledged at the durable append), the server is killed with tens of
// thousands of traces unapplied, one byte at a random place of a random
// segment of the log is flipped, and the server restarts. What is lost is
// at most the entry whose record holds the byte, and a loss is never
// silent: GetStats names it, /readyz and /metrics say DATA_LOSS.
// FLEETMEM_DAMAGE_TRIALS trials (2); docs/reliability.md has the runs.
#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <random>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
#include "tests/http_get.h"
#include "tests/server_process.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

constexpr char kFleet[] = "damaged";
constexpr size_t kMessage = 200;  // traces per upload message: one log entry

TEST(LogDamageTest, AFlippedByteLosesAtMostTheEntryItIsInAndSaysSo) {
  int trials = 2;
  if (const char* set = std::getenv("FLEETMEM_DAMAGE_TRIALS")) {
    trials = std::max(1, std::atoi(set));
  }
  std::mt19937_64 rng(44);
  uint64_t acknowledged_all = 0, missing_all = 0, lost_entries_all = 0;
  int reported = 0;
  for (int trial = 0; trial < trials; ++trial) {
    SCOPED_TRACE(absl::StrCat("trial ", trial));
    TempDir dir("fleetmem-damage-");
    ServerOptions options;
    options.data_dir = dir.Join("data");
    options.log_file = dir.Join("server.log");
    options.extra_args = {"--http-listen", "127.0.0.1:0"};
    const std::string config = dir.Join("server.textproto");
    // Nothing consolidated (every acknowledged trace stays); small
    // segments, so that the backlog spans several.
    std::ofstream(config) << "engine { segment_size: 1000000 }\n"
                          << "limits { max_traces_per_fleet: 10000000 }\n";
    options.config_file = config;
    auto server = std::make_unique<ServerProcess>(options);
    ASSERT_TRUE(server->Start().ok()) << server->Output();
    // Uploads acknowledged as durable, 10 messages a stream, until 40,000
    // traces are acknowledged.
    uint64_t acknowledged = 0;
    {
      auto stub = MakeStub(server->address());
      TraceSpec spec{
          .robot_id = "robot-1", .count = 10 * kMessage, .dimension = 64};
      for (uint64_t next = 1; acknowledged < 40000; next += spec.count) {
        spec.first_seq = next;
        const std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
        std::vector<v1::UploadTracesRequest> requests;
        for (size_t at = 0; at < traces.size(); at += kMessage) {
          v1::UploadTracesRequest& request = requests.emplace_back();
          request.set_fleet_id(kFleet);
          request.set_ack(v1::UPLOAD_ACK_DURABLE);
          for (size_t i = at; i < at + kMessage; ++i) {
            *request.add_traces() = traces[i];
          }
        }
        Reply<v1::UploadTracesResponse> reply = Upload(*stub, requests);
        ASSERT_TRUE(reply.ok()) << Describe(reply.status);
        acknowledged += reply.response.accepted();
      }
    }
    server->Kill();
    // One byte of a random segment, at a random place.
    std::vector<std::string> segments;
    for (const auto& entry : std::filesystem::directory_iterator(
             options.data_dir + "/db/ingest-log/f-" + kFleet)) {
      const std::string name = entry.path().filename().string();
      if (!name.starts_with("spare") && name.ends_with(".seg") &&
          entry.file_size() > 0) {
        segments.push_back(entry.path().string());
      }
    }
    ASSERT_FALSE(segments.empty());
    const std::string segment = segments[rng() % segments.size()];
    const uint64_t at = rng() % std::filesystem::file_size(segment);
    {
      const int fd = ::open(segment.c_str(), O_RDWR);
      ASSERT_GE(fd, 0);
      char byte = 0;
      ASSERT_EQ(::pread(fd, &byte, 1, static_cast<off_t>(at)), 1);
      byte = static_cast<char>(byte ^ (1 << (rng() % 8)));
      ASSERT_EQ(::pwrite(fd, &byte, 1, static_cast<off_t>(at)), 1);
      ::close(fd);
    }
    server = std::make_unique<ServerProcess>(options);
    ASSERT_TRUE(server->Start().ok()) << server->Output();
    auto stub = MakeStub(server->address());
    Reply<v1::GetStatsResponse> stats = GetStatsApplied(*stub, kFleet);
    ASSERT_TRUE(stats.ok()) << Describe(stats.status);
    EXPECT_EQ(stats.response.backlog_traces(), 0u);
    const v1::RobotStats* robot = FindRobot(stats.response, "robot-1");
    ASSERT_NE(robot, nullptr);
    uint64_t lost_entries = 0;
    for (const v1::LostLogEntries& lost : stats.response.log_entries_lost()) {
      lost_entries += lost.last_sequence() - lost.first_sequence() + 1;
    }
    const uint64_t missing =
        acknowledged > robot->received() ? acknowledged - robot->received() : 0;
    std::cout << "trial " << trial << ": byte " << at << " of "
              << std::filesystem::path(segment).filename().string() << " ("
              << segments.size() << " segments); " << acknowledged
              << " acknowledged, " << missing << " missing, " << lost_entries
              << " entries reported lost\n";
    // At most the entry the byte is in; never silently.
    EXPECT_LE(lost_entries, 1u);
    EXPECT_LE(missing, lost_entries * kMessage);
    if (missing > 0) EXPECT_GT(lost_entries, 0u) << "a silent loss";
    const std::string ready = HttpGet(server->http_address(), "/readyz");
    const std::string metrics = HttpGet(server->http_address(), "/metrics");
    if (lost_entries > 0) {
      ++reported;
      EXPECT_TRUE(absl::StrContains(ready, "DATA_LOSS fleet")) << ready;
      EXPECT_TRUE(absl::StrContains(
          metrics, absl::StrCat("fleetmem_log_entries_lost{fleet=\"", kFleet,
                                "\"} ", lost_entries)))
          << metrics;
      EXPECT_TRUE(absl::StrContains(server->Output(), "DATA_LOSS"));
    } else {
      EXPECT_FALSE(absl::StrContains(ready, "DATA_LOSS")) << ready;
    }
    EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(),
              robot->received());
    if (HasFailure()) std::cerr << server->Output();
    acknowledged_all += acknowledged;
    missing_all += missing;
    lost_entries_all += lost_entries;
    stub.reset();
    (void)server->Stop();
  }
  std::cout << trials << " trials: " << acknowledged_all << " acknowledged, "
            << missing_all << " missing, " << lost_entries_all
            << " entries reported lost in " << reported << " trials\n";
}

}  // namespace
}  // namespace fleetmem::testing
