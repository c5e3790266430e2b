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
#include <cerrno>
#include <cstring>
#include <fstream>
#include <iostream>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
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

TEST(DiskFullTest, RefusesWritesServesReadsAndRecovers) {
  TempDir dir("fleetmem-diskfull-");
  const std::string mount_point = dir.Join("fs");
  ASSERT_EQ(mkdir(mount_point.c_str(), 0700), 0);
  SmallFilesystem filesystem(mount_point, 48);
  if (!filesystem.mounted()) GTEST_SKIP() << filesystem.why_not();

  const std::string config = dir.Join("server.textproto");
  // Nothing is consolidated (so nothing is forgotten): every acknowledged
  // trace must stay in the fleet.
  std::ofstream(config) << "storage { min_free_bytes: " << 6 * kMiB
                        << " write_buffer_bytes: " << 2 * kMiB << " }\n"
                        << "engine { segment_size: 1000000 }\n";
  ServerOptions options;
  options.data_dir = mount_point + "/data";
  options.config_file = config;
  options.log_file = dir.Join("server.log");
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
  grpc::Status refused;
  for (int i = 0; i < 200 && refused.ok(); ++i) {
    spec.first_seq = 1 + acknowledged;
    Reply<v1::UploadTracesResponse> reply =
        UploadTraces(*stub, kFleet, MakeTraces(spec), kBatch);
    if (reply.ok()) {
      acknowledged += reply.response.accepted();
    } else {
      refused = reply.status;
      refusal(refused);
    }
  }
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
  // the process alive.
  const std::string last_bytes = mount_point + "/last-bytes";
  Fill(last_bytes, FreeBytes(mount_point));
  // RocksDB may free files (compaction) meanwhile: top up.
  for (int i = 0; i < 5 && FreeBytes(mount_point) >= kMiB; ++i) {
    Fill(last_bytes + std::to_string(i), FreeBytes(mount_point));
  }
  EXPECT_LT(FreeBytes(mount_point), kMiB);
  spec.first_seq = 1 + acknowledged;
  const grpc::Status still =
      UploadTraces(*stub, kFleet, MakeTraces(spec)).status;
  ASSERT_FALSE(still.ok());
  refusal(still);
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
  const grpc::Status after_crash =
      UploadTraces(*stub, kFleet, MakeTraces(spec)).status;
  ASSERT_FALSE(after_crash.ok());
  refusal(after_crash);

  // Space returns: writes resume by themselves.
  ASSERT_EQ(unlink(filler.c_str()), 0);
  ASSERT_EQ(unlink(last_bytes.c_str()), 0);
  for (int i = 0; i < 5; ++i) unlink((last_bytes + std::to_string(i)).c_str());
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

}  // namespace
}  // namespace fleetmem::testing
