// The server on a small filesystem that fills up: reads go on, writes are
// refused with a clear status, the process never aborts, writes resume by
// themselves once space is freed, and every acknowledged trace is still
// there after a kill -9. The filesystem is a tmpfs the test mounts (needs
// root; skipped with a message otherwise).
#include <sys/mount.h>
#include <sys/stat.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "rocksdb/env.h"
#include "services/common/log.h"
#include "services/storage/rocksdb_info_log.h"
#include "tests/api_helpers.h"
#include "tests/http_get.h"
#include "tests/server_process.h"
#include "tests/small_filesystem.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

constexpr char kFleet[] = "full";
constexpr size_t kBatch = 200;

// The store's reserve file (storage/rocksdb_store.cc) under `data_dir`.
bool HasReserveFile(const std::string& data_dir) {
  struct stat info;
  return stat((data_dir + "/db.reserve").c_str(), &info) == 0;
}

// A server whose data lives on the small filesystem at `mount_point`: a
// reserve of 6 MiB, small memtables, and nothing consolidated (so nothing is
// forgotten: every acknowledged trace must stay in the fleet).
ServerOptions SmallDiskServer(const TempDir& dir,
                              const std::string& mount_point) {
  const std::string config = dir.Join("server.textproto");
  std::ofstream(config) << "storage { min_free_bytes: " << 6 * kMiB
                        << " write_buffer_bytes: " << 2 * kMiB << " }\n"
                        << "engine { segment_size: 1000000 }\n";
  ServerOptions options;
  options.data_dir = mount_point + "/data";
  options.config_file = config;
  options.log_file = dir.Join("server.log");
  return options;
}

// Takes every free byte under `mount_point` (RocksDB may free files
// meanwhile: topped up a few times), in files named `prefix`N.
void FillUp(const std::string& mount_point, const std::string& prefix) {
  for (int i = 0; i < 5 && FreeBytes(mount_point) > 0; ++i) {
    Fill(mount_point + "/" + prefix + std::to_string(i),
         FreeBytes(mount_point));
  }
}

TEST(DiskFullTest, RefusesWritesServesReadsAndRecovers) {
  TempDir dir("fleetmem-diskfull-");
  const std::string mount_point = dir.Join("fs");
  ASSERT_EQ(mkdir(mount_point.c_str(), 0700), 0);
  SmallFilesystem filesystem(mount_point, 48);
  if (!filesystem.mounted()) GTEST_SKIP() << filesystem.why_not();

  const ServerOptions options = SmallDiskServer(dir, mount_point);
  auto server = std::make_unique<ServerProcess>(options);
  // On failure, show what the server said (a crash names its cause there).
  struct PrintLogOnFailure {
    std::string log_file;
    ~PrintLogOnFailure() {
      if (::testing::Test::HasFailure()) {
        std::cerr << "---- fleetmem-server output ----\n"
                  << ReadFileOrEmpty(log_file) << "\n---- end ----\n";
      }
    }
  } print_log{options.log_file};
  ASSERT_TRUE(server->Start().ok()) << server->Output();
  auto stub = MakeStub(server->address());

  // Leave about 10 MiB free: room for a few MiB of traces above the reserve.
  const std::string filler = mount_point + "/filler";
  Fill(filler, FreeBytes(mount_point) - 10 * kMiB);

  TraceSpec spec;
  spec.robot_id = "robot-1";
  spec.dimension = 256;
  spec.count = kBatch;
  uint64_t acknowledged = 0;
  // A refused upload: the full disk refused its append to the log (nothing
  // stored), or the apply it waited for (the upload asks to be acknowledged
  // once applied): its traces are durable in the log then, and the status
  // says so.
  auto refusal = [&](const grpc::Status& status) {
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED)
        << Describe(status);
    EXPECT_TRUE(absl::StrContains(status.error_message(), "disk nearly full"))
        << Describe(status);
    if (absl::StrContains(status.error_message(),
                          "are durable and acknowledged")) {
      acknowledged += spec.count;  // every seq of the batch was new
    } else {
      EXPECT_TRUE(
          absl::StrContains(status.error_message(), "nothing was stored"))
          << Describe(status);
    }
  };
  // Uploads new batches until one is refused; returns that refusal (OK if
  // none was in 200). Space the server frees itself (the ingest log's spare
  // segment, files RocksDB deletes, a log segment trimmed after an apply)
  // takes a few more batches first, so a full disk is a refusal within the
  // loop, not at its first upload.
  auto upload_until_refused = [&]() -> grpc::Status {
    for (int i = 0; i < 200; ++i) {
      spec.first_seq = 1 + acknowledged;
      Reply<v1::UploadTracesResponse> reply =
          UploadTraces(*stub, kFleet, MakeTraces(spec), kBatch);
      if (!reply.ok()) {
        refusal(reply.status);
        return reply.status;
      }
      acknowledged += reply.response.accepted();
    }
    return grpc::Status::OK;
  };
  const grpc::Status refused = upload_until_refused();
  ASSERT_FALSE(refused.ok()) << "the filesystem never filled up";
  ASSERT_GT(acknowledged, 0u);

  // Reads are served and hold exactly what was acknowledged (applied, or
  // durable in the log and waiting).
  Reply<v1::GetStatsResponse> stats = GetStats(*stub, kFleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces() +
                stats.response.backlog_traces(),
            acknowledged);
  spec.first_seq = 1;
  std::vector<float> code = CodeOf(MakeTrace(spec, 1));
  EXPECT_TRUE(QueryCode(*stub, kFleet, code, 3).ok());
  // Another process takes the last byte: still refused, reads still served,
  // the process alive. (RocksDB then fails its own background writes; its
  // info log, written to a file here before, aborted the server on its next
  // line: storage/rocksdb_info_log.h.)
  FillUp(mount_point, "last-bytes");
  EXPECT_LT(FreeBytes(mount_point), kMiB);
  const grpc::Status still = upload_until_refused();
  ASSERT_FALSE(still.ok());
  EXPECT_TRUE(GetStats(*stub, kFleet).ok());
  EXPECT_TRUE(QueryCode(*stub, kFleet, code, 3).ok());
  EXPECT_TRUE(server->running());
  std::cout << "acknowledged " << acknowledged
            << " traces before the disk filled\n";

  // A crash while the filesystem is full: the restart in place opens (it
  // aborted in RocksDB's open before the reserve file, issue 32), serves
  // reads and refuses writes.
  EXPECT_TRUE(HasReserveFile(options.data_dir));
  stub.reset();
  server->Kill();
  server = std::make_unique<ServerProcess>(options);
  ASSERT_TRUE(server->Start().ok()) << server->Output();
  stub = MakeStub(server->address());
  stats = GetStats(*stub, kFleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces() +
                stats.response.backlog_traces(),
            acknowledged);
  EXPECT_TRUE(QueryCode(*stub, kFleet, code, 3).ok());
  // What the killed process held open (files RocksDB had deleted) is free
  // now: another process takes it.
  FillUp(mount_point, "after-crash");
  const grpc::Status after_crash = upload_until_refused();
  ASSERT_FALSE(after_crash.ok());

  // Space returns: writes resume by themselves.
  spec.first_seq = 1 + acknowledged;
  ASSERT_EQ(unlink(filler.c_str()), 0);
  for (const char* prefix : {"/last-bytes", "/after-crash"}) {
    for (int i = 0; i < 5; ++i) {
      unlink(absl::StrCat(mount_point, prefix, i).c_str());
    }
  }
  Reply<v1::UploadTracesResponse> resumed =
      UploadTraces(*stub, kFleet, MakeTraces(spec));
  ASSERT_TRUE(resumed.ok()) << Describe(resumed.status);
  acknowledged += resumed.response.accepted();
  EXPECT_TRUE(HasReserveFile(options.data_dir));  // taken again

  // Every acknowledged trace survives a kill -9 and a restart in place.
  stub.reset();
  server->Kill();
  server = std::make_unique<ServerProcess>(options);
  ASSERT_TRUE(server->Start().ok()) << server->Output();
  stub = MakeStub(server->address());
  stats = GetStats(*stub, kFleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(),
            acknowledged);
  const v1::RobotStats* robot = FindRobot(stats.response, "robot-1");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->received(), acknowledged);
  stub.reset();
  absl::StatusOr<int> code_on_stop = server->Stop();
  EXPECT_TRUE(code_on_stop.ok() && *code_on_stop == 0);
  if (HasFailure()) std::cerr << server->Output();
}

// Issue 32: a store never written to, on a filesystem another process has
// filled. The reserve file is taken at the first open, so the restart opens
// (reads served, writes refused); once that file has been given back and
// the space taken too, the open is refused with a clear error (no abort in
// RocksDB's open); space freed, the server starts and writes again.
TEST(DiskFullTest, AStoreNeverWrittenToRestartsOnAFilledDisk) {
  TempDir dir("fleetmem-diskopen-");
  const std::string mount_point = dir.Join("fs");
  ASSERT_EQ(mkdir(mount_point.c_str(), 0700), 0);
  SmallFilesystem filesystem(mount_point, 48);
  if (!filesystem.mounted()) GTEST_SKIP() << filesystem.why_not();
  const ServerOptions options = SmallDiskServer(dir, mount_point);
  {
    ServerProcess server(options);
    ASSERT_TRUE(server.Start().ok()) << server.Output();
    EXPECT_EQ(server.Stop().value_or(-1), 0);
  }
  EXPECT_TRUE(HasReserveFile(options.data_dir));

  FillUp(mount_point, "first");
  TraceSpec spec{.robot_id = "robot-1", .count = 10, .dimension = 256};
  {
    ServerProcess server(options);
    ASSERT_TRUE(server.Start().ok()) << server.Output();
    const grpc::Status refused =
        UploadTraces(*MakeStub(server.address()), kFleet, MakeTraces(spec))
            .status;
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED)
        << Describe(refused);
    EXPECT_EQ(server.Stop().value_or(-1), 0) << server.Output();
  }
  EXPECT_FALSE(HasReserveFile(options.data_dir));  // given back at open

  FillUp(mount_point, "second");
  {
    ServerProcess server(options);
    const absl::Status started = server.Start();
    ASSERT_FALSE(started.ok());
    EXPECT_TRUE(absl::StrContains(started.message(), "disk nearly full"))
        << started;
    EXPECT_TRUE(absl::StrContains(started.message(), "nothing was opened"))
        << started;
    EXPECT_FALSE(absl::StrContains(started.message(), "Assertion")) << started;
  }

  for (const char* prefix : {"first", "second"}) {
    for (int i = 0; i < 5; ++i) {
      unlink((mount_point + "/" + prefix + std::to_string(i)).c_str());
    }
  }
  ServerProcess server(options);
  ASSERT_TRUE(server.Start().ok()) << server.Output();
  Reply<v1::UploadTracesResponse> written =
      UploadTraces(*MakeStub(server.address()), kFleet, MakeTraces(spec));
  ASSERT_TRUE(written.ok()) << Describe(written.status);
  EXPECT_EQ(written.response.accepted(), spec.count);
  EXPECT_TRUE(HasReserveFile(options.data_dir));
  EXPECT_EQ(server.Stop().value_or(-1), 0);
}

// Why the store keeps RocksDB's info log off the disk
// (storage/rocksdb_info_log.h). RocksDB's own info log (Env::NewLogger, the
// LOG file) on a filesystem another process filled: its writer fails a
// flush, and its next line aborts the process (Debian's RocksDB 7.8.3:
// "sync_without_flush_called_"); the server's info log, the same lines,
// goes on. Disabled: the first half shows a fault of one RocksDB build, not
// of fleetmem (docs/reliability.md has the runs); run it with
// --gtest_also_run_disabled_tests.
TEST(DiskFullTest, DISABLED_RocksDbsOwnInfoLogAbortsOnAFullDiskTheServersNot) {
  TempDir dir("fleetmem-infolog-");
  const std::string mount_point = dir.Join("fs");
  ASSERT_EQ(mkdir(mount_point.c_str(), 0700), 0);
  SmallFilesystem filesystem(mount_point, 16);
  if (!filesystem.mounted()) GTEST_SKIP() << filesystem.why_not();
  // Lines of warnings (each flushed) and errors, as RocksDB logs a
  // background error the full disk caused.
  auto log_lines = [](rocksdb::Logger* logger) {
    const std::string detail(2048, 'x');
    for (int i = 0; i < 64; ++i) {
      rocksdb::Log(rocksdb::InfoLogLevel::WARN_LEVEL, logger,
                   "background error %d: IO error: No space left %s", i,
                   detail.c_str());
    }
  };
  EXPECT_DEATH(
      {
        std::shared_ptr<rocksdb::Logger> own;
        if (!rocksdb::Env::Default()
                 ->NewLogger(mount_point + "/LOG", &own)
                 .ok()) {
          std::exit(3);
        }
        // At the level DB::Open sets (Options::info_log_level).
        own->SetInfoLogLevel(rocksdb::InfoLogLevel::INFO_LEVEL);
        Fill(mount_point + "/filler", FreeBytes(mount_point));
        log_lines(own.get());
      },
      "sync_without_flush_called_");
  unlink((mount_point + "/filler").c_str());
  Fill(mount_point + "/filler", FreeBytes(mount_point));
  const log::Level level = log::GetLevel();
  log::SetLevel(log::Level::kError);  // the lines are not the point here
  log_lines(storage::NewRocksDbInfoLog().get());
  log::SetLevel(level);
  EXPECT_EQ(FreeBytes(mount_point), 0u);
}

// Issue 32: another process filling the filesystem *during* uploads (the
// test above fills it between them). Each trial: a robot uploads without
// pause; another writer takes every free byte at a seeded moment; the server
// must stay up; once the space is freed, uploads must succeed again within
// the documented 8 s; after a kill -9 and a restart in place, every
// acknowledged trace is there. FLEETMEM_DISK_TRIALS sets the number of
// trials (3 in `make test`; docs/reliability.md reports 20).
// The filesystem sizes of the outside-fill trials: FLEETMEM_DISK_SIZES_MIB
// ("24,48,96"), 48 by default.
std::vector<int> TrialSizes() {
  std::vector<int> sizes;
  const char* set = std::getenv("FLEETMEM_DISK_SIZES_MIB");
  for (absl::string_view size : absl::StrSplit(set ? set : "48", ',')) {
    int mib = 0;
    if (absl::SimpleAtoi(size, &mib) && mib >= 16) sizes.push_back(mib);
  }
  return sizes;
}

// Another process fills the filesystem while a robot uploads without pause
// (the outside sweep: RocksDB aborted in 3 of 30 such trials, its
// write-ahead log written again after a failed append). Each trial: the
// server must stay up; while its log cannot be applied, /readyz and
// /metrics say so within 10 s; the other writer's files go (half of the
// trials after a kill -9 with the disk still full), uploads succeed again
// within 8 s (or, after the kill, the restart applies the log), and every
// acknowledged trace is there after a kill -9 and a restart.
// FLEETMEM_DISK_TRIALS (3) trials on each of TrialSizes();
// docs/reliability.md has the runs.
TEST(DiskFullTest, AnOutsideWriterFillingTheDiskDuringUploads) {
  int trials = 3;
  if (const char* set = std::getenv("FLEETMEM_DISK_TRIALS")) {
    trials = std::max(1, std::atoi(set));
  }
  std::mt19937 rng(32);
  double slowest_resume = 0;
  int died = 0;
  int stuck_seen = 0;
  int filled_by_own_data = 0;
  int waiting_after_restart = 0;
  int runs = 0;
  for (const int size_mib : TrialSizes()) {
    for (int trial = 0; trial < trials; ++trial, ++runs) {
      SCOPED_TRACE(absl::StrCat(size_mib, " MiB, trial ", trial));
      const bool kill_while_full = trial % 2 == 1;
      TempDir dir("fleetmem-diskfill-");
      const std::string mount_point = dir.Join("fs");
      ASSERT_EQ(mkdir(mount_point.c_str(), 0700), 0);
      SmallFilesystem filesystem(mount_point, size_mib);
      if (!filesystem.mounted()) GTEST_SKIP() << filesystem.why_not();
      ServerOptions options = SmallDiskServer(dir, mount_point);
      options.extra_args = {"--http-listen", "127.0.0.1:0"};
      auto server = std::make_unique<ServerProcess>(options);
      ASSERT_TRUE(server->Start().ok()) << server->Output();
      // Leave 18 MiB or so, so that the fill comes within a second or two.
      const uint64_t free = FreeBytes(mount_point);
      if (free > 18 * kMiB) Fill(mount_point + "/ballast", free - 18 * kMiB);

      std::atomic<bool> stop = false;
      std::atomic<uint64_t> acknowledged = 0;
      std::atomic<uint64_t> successes = 0;
      std::thread robot([&] {
        auto stub = MakeStub(server->address());
        TraceSpec spec{
            .robot_id = "robot-1", .count = kBatch, .dimension = 256};
        uint64_t next = 1;
        while (!stop.load()) {
          spec.first_seq = next;
          Reply<v1::UploadTracesResponse> reply =
              UploadTraces(*stub, kFleet, MakeTraces(spec), kBatch);
          if (reply.ok()) {
            acknowledged += reply.response.accepted();
            ++successes;
            next += kBatch;
          } else if (absl::StrContains(reply.status.error_message(),
                                       "are durable and acknowledged")) {
            acknowledged += kBatch;
            next += kBatch;
          } else {
            std::this_thread::sleep_for(std::chrono::milliseconds(20));
          }
        }
      });
      // The fleet exists before the disk fills (its first upload is
      // acknowledged: under a sanitizer the server may take longer than the
      // wait below to answer it, and a fleet never acknowledged rightly does
      // not exist after the restart).
      const auto started = std::chrono::steady_clock::now();
      while (successes.load() == 0 &&
             std::chrono::steady_clock::now() - started <
                 std::chrono::seconds(30)) {
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
      }
      EXPECT_GT(successes.load(), 0u) << server->Output();
      std::this_thread::sleep_for(std::chrono::milliseconds(
          std::uniform_int_distribution<int>(50, 600)(rng)));
      const std::string filler = mount_point + "/filler";
      Fill(filler, FreeBytes(mount_point));
      for (int i = 0; i < 3 && FreeBytes(mount_point) > 0; ++i) {
        Fill(filler + std::to_string(i), FreeBytes(mount_point));
      }
      std::this_thread::sleep_for(std::chrono::seconds(1));
      EXPECT_TRUE(server->running()) << "the server died with the disk full";
      if (!server->running()) {
        ++died;
        stop = true;
        robot.join();
        const std::string output = server->Output();
        std::cerr << output.substr(output.size() > 3000 ? output.size() - 3000
                                                        : 0);
        continue;
      }
      // A backlog that cannot be applied is loud within 10 s.
      {
        auto stub = MakeStub(server->address());
        Reply<v1::GetStatsResponse> stats = GetStats(*stub, kFleet);
        if (stats.ok() && stats.response.backlog_entries() > 0) {
          std::string ready;
          std::string metrics;
          const auto asked = std::chrono::steady_clock::now();
          while (std::chrono::steady_clock::now() - asked <
                 std::chrono::seconds(10)) {
            ready = HttpGet(server->http_address(), "/readyz");
            metrics = HttpGet(server->http_address(), "/metrics");
            if (absl::StrContains(ready, "STUCK fleet \"full\"")) break;
            std::this_thread::sleep_for(std::chrono::milliseconds(200));
          }
          stats = GetStats(*stub, kFleet);
          if (stats.ok() && stats.response.backlog_entries() > 0) {
            ++stuck_seen;
            EXPECT_TRUE(absl::StrContains(ready, "STUCK fleet \"full\""))
                << ready;
            EXPECT_TRUE(absl::StrContains(
                metrics, "fleetmem_write_apply_blocked{fleet=\"full\"} 1"))
                << metrics;
          }
        }
      }
      if (kill_while_full) {
        stop = true;
        robot.join();
        EXPECT_TRUE(server->running()) << server->Output();
        if (!server->running()) ++died;
        server->Kill();
      }
      // Space returns (the test's ballast too: the robot may have filled the
      // rest itself before the other writer came).
      unlink((mount_point + "/ballast").c_str());
      unlink(filler.c_str());
      for (int i = 0; i < 3; ++i) unlink((filler + std::to_string(i)).c_str());
      // On the smallest filesystems the store's own data (its log, tables,
      // reserve file) may leave less than its reserve free once the other
      // writer's files are gone: writes are then rightly refused, and the
      // backlog waits, reported, until space is freed (checked below).
      const bool own_data_fills_it = FreeBytes(mount_point) < 8 * kMiB;
      if (own_data_fills_it) ++filled_by_own_data;
      if (!kill_while_full && own_data_fills_it) {
        stop = true;
        robot.join();
        EXPECT_TRUE(server->running()) << server->Output();
        if (!server->running()) ++died;
        server->Kill();
      } else if (!kill_while_full) {
        // Time until an upload succeeds again.
        const uint64_t before = successes.load();
        const auto freed = std::chrono::steady_clock::now();
        while (successes.load() == before &&
               std::chrono::steady_clock::now() - freed <
                   std::chrono::seconds(60)) {
          std::this_thread::sleep_for(std::chrono::milliseconds(10));
        }
        const double resume = std::chrono::duration<double>(
                                  std::chrono::steady_clock::now() - freed)
                                  .count();
        slowest_resume = std::max(slowest_resume, resume);
        EXPECT_LE(resume, 8.0)
            << "writes came back " << resume << " s after space was freed";
        if (HasFailure()) std::cerr << server->Output();
        stop = true;
        robot.join();
        EXPECT_TRUE(server->running()) << server->Output();
        if (!server->running()) ++died;
        server->Kill();
      }
      // Every acknowledged trace survives a kill -9 and a restart in place
      // (a lambda: a failed check ends this trial, not the run).
      [&] {
        server = std::make_unique<ServerProcess>(options);
        ASSERT_TRUE(server->Start().ok()) << server->Output();
        auto stub = MakeStub(server->address());
        // Once the restart has applied what its log holds.
        Reply<v1::GetStatsResponse> stats =
            GetStatsApplied(*stub, kFleet,
                            own_data_fills_it ? std::chrono::seconds(5)
                                              : std::chrono::seconds(120));
        ASSERT_TRUE(stats.ok()) << Describe(stats.status);
        const v1::RobotStats* robot_stats =
            FindRobot(stats.response, "robot-1");
        ASSERT_NE(robot_stats, nullptr);
        // Applied, or waiting (durable, reported) for space to apply them.
        EXPECT_GE(robot_stats->received() + stats.response.backlog_traces(),
                  acknowledged.load());
        if (stats.response.backlog_traces() > 0) {
          ++waiting_after_restart;
          EXPECT_THAT(stats.response.apply_error(),
                      ::testing::HasSubstr("disk nearly full"));
          EXPECT_TRUE(
              absl::StrContains(HttpGet(server->http_address(), "/readyz"),
                                "STUCK fleet \"full\""));
        }
        EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(),
                  robot_stats->received());
        EXPECT_EQ(stats.response.log_entries_lost_size(), 0);
        if (HasFailure()) std::cerr << server->Output();
        stub.reset();
        (void)server->Stop();
      }();
    }
  }
  std::cout << runs << " trials; " << died
            << " in which the server died; slowest resume " << slowest_resume
            << " s; a stuck backlog seen (and reported) in " << stuck_seen
            << "; the store's own data left less than its reserve free in "
            << filled_by_own_data << " (a backlog waiting after the restart: "
            << waiting_after_restart << ")\n";
}

}  // namespace
}  // namespace fleetmem::testing
