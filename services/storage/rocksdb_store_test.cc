// Tests specific to the RocksDB store: reopening, crashes, open errors and
// corrupt records. (Semantics shared with the in-memory store are in
// memory_store_test.cc.)
#include "services/storage/rocksdb_store.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>
#include <xxhash.h>

#include <atomic>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <map>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "rocksdb/db.h"
#include "rocksdb/env.h"
#include "services/common/log.h"
#include "services/storage/in_memory_store.h"
#include "services/storage/keys.h"
#include "services/storage/record_codec.h"
#include "services/storage/rocksdb_info_log.h"
#include "services/storage/snapshot_file.h"
#include "services/storage/testing/store_test_util.h"

extern char** environ;

namespace fleetmem::storage {
namespace {

using engine::FleetMutation;
using engine::FleetRecord;
using testing::Dump;
using ::testing::HasSubstr;
using testing::ScriptedMutations;
using testing::TempDir;

std::unique_ptr<engine::MemoryStore> OpenOrDie(const std::string& path,
                                               bool sync = true) {
  RocksDbStoreOptions options;
  options.path = path;
  options.sync = sync;
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
      OpenRocksDbStore(options);
  EXPECT_TRUE(store.ok()) << store.status();
  return store.ok() ? std::move(*store) : nullptr;
}

// Dump of the fleet and of all its events, or of the error.
std::string DumpFleet(engine::MemoryStore& store, std::string_view fleet_id) {
  absl::StatusOr<FleetRecord> record = store.LoadFleet(fleet_id);
  if (!record.ok()) return record.status().ToString();
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      store.ReadEvents(fleet_id, 0, 100000);
  if (!events.ok()) return events.status().ToString();
  return absl::StrCat(Dump(*record), Dump(*events));
}

// The expected dump of `fleet_id` after the first `count` mutations of
// `script`, from the in-memory store.
std::string ReferenceDump(const std::vector<FleetMutation>& script,
                          size_t count, std::string_view fleet_id) {
  std::unique_ptr<engine::MemoryStore> reference = NewInMemoryStore();
  for (size_t i = 0; i < count; ++i) {
    EXPECT_TRUE(reference->Apply(fleet_id, script[i]).ok());
  }
  return DumpFleet(*reference, fleet_id);
}

TEST(RocksDbStoreTest, ReopenGivesExactlyTheSameRecords) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  const std::vector<std::string> fleets = {"f", "f1", "fleet-b"};
  std::vector<std::string> before;
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    for (size_t i = 0; i < fleets.size(); ++i) {
      for (const FleetMutation& m : ScriptedMutations(30 + 10 * i)) {
        ASSERT_TRUE(store->Apply(fleets[i], m).ok());
      }
      before.push_back(DumpFleet(*store, fleets[i]));
      EXPECT_EQ(before.back(), ReferenceDump(ScriptedMutations(30 + 10 * i),
                                             30 + 10 * i, fleets[i]));
    }
  }
  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(store->ListFleets().value_or(std::vector<std::string>{}), fleets);
  for (size_t i = 0; i < fleets.size(); ++i) {
    EXPECT_EQ(DumpFleet(*store, fleets[i]), before[i]) << fleets[i];
  }
}

// Aliases live beside the fleets (engine::StoredAliases reads them back at
// start-up) and are no fleet's.
TEST(RocksDbStoreTest, AliasesSurviveAReopenAndAreNoFleets) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    ASSERT_TRUE(store->Apply("f", ScriptedMutations(5).front()).ok());
    ASSERT_TRUE(store->PutAlias("live", "f").ok());
    ASSERT_TRUE(store->PutAlias("gone", "f").ok());
    ASSERT_TRUE(store->PutAlias("gone", "").ok());
    ASSERT_TRUE(store->PutAlias("z:1", "other").ok());
  }
  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
  ASSERT_NE(store, nullptr);
  EXPECT_EQ(store->ListFleets().value_or(std::vector<std::string>{}),
            std::vector<std::string>{"f"});
  absl::StatusOr<std::vector<engine::FleetAlias>> aliases =
      store->LoadAliases();
  ASSERT_TRUE(aliases.ok()) << aliases.status();
  ASSERT_EQ(aliases->size(), 2u);
  EXPECT_EQ((*aliases)[0].alias, "live");
  EXPECT_EQ((*aliases)[0].fleet_id, "f");
  EXPECT_EQ((*aliases)[1].alias, "z:1");
  EXPECT_EQ((*aliases)[1].fleet_id, "other");
}

// The memory report names RocksDB's own memory; what is written sits in the
// memtables until a flush, what is read in the block cache.
TEST(RocksDbStoreTest, MemoryUsageNamesMemtablesTableReadersAndCache) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
  ASSERT_NE(store, nullptr);
  auto usage = [&store] {
    std::map<std::string, uint64_t> by_kind;
    for (const auto& [kind, bytes] : store->MemoryUsage())
      by_kind[kind] = bytes;
    return by_kind;
  };
  const std::map<std::string, uint64_t> empty = usage();
  for (const char* kind :
       {"memtables", "table_readers", "block_cache", "block_cache_pinned"}) {
    EXPECT_TRUE(empty.contains(kind)) << kind;
  }
  for (const FleetMutation& m : ScriptedMutations(40)) {
    ASSERT_TRUE(store->Apply("f", m).ok());
  }
  EXPECT_GT(usage()["memtables"], empty.at("memtables"));
}

// RocksDB's info log is the server's log: no LOG file is written beside the
// data (its writes aborted the server on a full disk, rocksdb_info_log.h),
// and RocksDB's warnings reach stderr; its info lines are not kept.
TEST(RocksDbStoreTest, InfoLogGoesToTheServerLogNotToAFile) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    for (const FleetMutation& m : ScriptedMutations(40)) {
      ASSERT_TRUE(store->Apply("f", m).ok());
    }
  }
  for (const auto& entry : std::filesystem::directory_iterator(path)) {
    EXPECT_FALSE(entry.path().filename().string().starts_with("LOG"))
        << entry.path();
  }

  const log::Level before = log::GetLevel();
  log::SetLevel(log::Level::kDebug);  // RocksDB's info lines not even then
  std::shared_ptr<rocksdb::Logger> info_log = NewRocksDbInfoLog();
  ::testing::internal::CaptureStderr();
  rocksdb::Log(rocksdb::InfoLogLevel::WARN_LEVEL, info_log.get(),
               "background error %d", 28);
  rocksdb::Log(rocksdb::InfoLogLevel::INFO_LEVEL, info_log.get(),
               "compaction stats %d", 1);
  rocksdb::Header(info_log.get(), "Options.error_if_exists: %d", 0);
  const std::string printed = ::testing::internal::GetCapturedStderr();
  log::SetLevel(before);
  EXPECT_THAT(printed, HasSubstr(" W rocksdb:0] background error 28\n"));
  EXPECT_THAT(printed, ::testing::Not(HasSubstr("compaction stats")));
  EXPECT_THAT(printed, ::testing::Not(HasSubstr("Options.")));
}

constexpr char kChildDirEnv[] = "FLEETMEM_STORAGE_CRASH_DIR";
constexpr char kChildCountEnv[] = "FLEETMEM_STORAGE_CRASH_COUNT";
constexpr char kChildSyncEnv[] = "FLEETMEM_STORAGE_CRASH_SYNC";
constexpr char kChildAckFdEnv[] = "FLEETMEM_STORAGE_CRASH_ACK_FD";
constexpr char kCrashFleet[] = "crash";

// The child of RocksDbCrashTest, started by it through fork + exec of this
// binary (a fresh process, so no RocksDB thread state is inherited). Applies
// the scripted mutations, writes one byte to the ack pipe after each OK, then
// kills itself without closing the database.
TEST(RocksDbCrashChild, DISABLED_ApplyThenDie) {
  const char* dir = std::getenv(kChildDirEnv);
  if (dir == nullptr) GTEST_SKIP() << "runs only as RocksDbCrashTest's child";
  const int count = std::atoi(std::getenv(kChildCountEnv));
  const bool sync = std::string(std::getenv(kChildSyncEnv)) == "1";
  const int ack_fd = std::atoi(std::getenv(kChildAckFdEnv));
  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(dir, sync);
  if (store == nullptr) _exit(2);
  for (const FleetMutation& m : ScriptedMutations(count)) {
    if (!store->Apply(kCrashFleet, m).ok()) _exit(3);
    if (write(ack_fd, "+", 1) != 1) _exit(4);
  }
  raise(SIGKILL);
  _exit(5);  // not reached
}

struct CrashCase {
  std::string name;
  bool sync = true;
  int script_length = 0;
  // 0: the child kills itself after the whole script; otherwise the parent
  // kills it as soon as this many mutations are acknowledged, probably in
  // the middle of a write.
  int kill_after_acks = 0;
};

void PrintTo(const CrashCase& c, std::ostream* os) { *os << c.name; }

class RocksDbCrashTest : public ::testing::TestWithParam<CrashCase> {};

TEST_P(RocksDbCrashTest, AcknowledgedMutationsSurviveSigkill) {
  const CrashCase& c = GetParam();
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  int ack[2];
  ASSERT_EQ(pipe(ack), 0);

  // Everything the child needs is prepared before fork: after it, only
  // async-signal-safe calls.
  char self[4096];
  const ssize_t self_length =
      readlink("/proc/self/exe", self, sizeof(self) - 1);
  ASSERT_GT(self_length, 0);
  self[self_length] = '\0';
  std::vector<std::string> args = {
      self, "--gtest_filter=RocksDbCrashChild.DISABLED_ApplyThenDie",
      "--gtest_also_run_disabled_tests"};
  std::vector<std::string> env;
  for (char** e = environ; *e != nullptr; ++e) env.emplace_back(*e);
  env.push_back(absl::StrCat(kChildDirEnv, "=", path));
  env.push_back(absl::StrCat(kChildCountEnv, "=", c.script_length));
  env.push_back(absl::StrCat(kChildSyncEnv, "=", c.sync ? "1" : "0"));
  env.push_back(absl::StrCat(kChildAckFdEnv, "=", ack[1]));
  std::vector<char*> argv;
  for (std::string& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  std::vector<char*> envp;
  for (std::string& e : env) envp.push_back(e.data());
  envp.push_back(nullptr);

  const pid_t pid = fork();
  ASSERT_GE(pid, 0);
  if (pid == 0) {
    close(ack[0]);
    const int null = open("/dev/null", O_WRONLY);
    if (null >= 0) dup2(null, STDOUT_FILENO);
    execve(argv[0], argv.data(), envp.data());
    _exit(127);
  }
  close(ack[1]);
  int acked = 0;
  char buffer[256];
  bool killed = false;
  for (;;) {
    const ssize_t n = read(ack[0], buffer, sizeof(buffer));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) break;  // EOF: the child is gone
    acked += static_cast<int>(n);
    if (c.kill_after_acks > 0 && !killed && acked >= c.kill_after_acks) {
      kill(pid, SIGKILL);
      killed = true;
    }
  }
  close(ack[0]);
  RecordProperty("acked", acked);
  int wait_status = 0;
  ASSERT_EQ(waitpid(pid, &wait_status, 0), pid);
  ASSERT_TRUE(WIFSIGNALED(wait_status))
      << "child exited with " << WEXITSTATUS(wait_status);
  EXPECT_EQ(WTERMSIG(wait_status), SIGKILL);
  if (c.kill_after_acks == 0) {
    ASSERT_EQ(acked, c.script_length);
  } else {
    ASSERT_GE(acked, c.kill_after_acks);
  }

  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
  ASSERT_NE(store, nullptr);
  const std::string got = DumpFleet(*store, kCrashFleet);
  const std::vector<FleetMutation> script = ScriptedMutations(c.script_length);
  const std::string after_acked = ReferenceDump(script, acked, kCrashFleet);
  if (got == after_acked) return;
  // Killed between a durable write and its ack: one more mutation is there,
  // whole (never a part of one).
  ASSERT_LT(acked, c.script_length) << "acked " << acked;
  EXPECT_EQ(got, ReferenceDump(script, acked + 1, kCrashFleet))
      << "acked " << acked;
}

INSTANTIATE_TEST_SUITE_P(
    Kill, RocksDbCrashTest,
    ::testing::Values(CrashCase{"SyncChildKillsItself", true, 40, 0},
                      CrashCase{"NoSyncChildKillsItself", false, 40, 0},
                      CrashCase{"SyncKilledMidStream", true, 400, 25},
                      CrashCase{"NoSyncKilledMidStream", false, 400, 100}),
    [](const auto& info) { return info.param.name; });

// --- Open errors.

TEST(RocksDbStoreTest, OpenOnUnwritablePathGivesAClearError) {
  TempDir dir;
  const std::string file = absl::StrCat(dir.path(), "/plain-file");
  std::ofstream(file) << "not a directory";
  struct Case {
    std::string path;
    bool create_if_missing;
    absl::StatusCode code;
  };
  std::vector<Case> cases = {
      // Below a regular file: no one, not even root, can create it.
      {absl::StrCat(file, "/db"), true, absl::StatusCode::kUnavailable},
      {file, true, absl::StatusCode::kUnavailable},
      {absl::StrCat(dir.path(), "/missing"), false,
       absl::StatusCode::kInvalidArgument},
  };
  if (geteuid() != 0) {  // permissions do not bind root
    const std::string read_only = absl::StrCat(dir.path(), "/read-only");
    ASSERT_EQ(mkdir(read_only.c_str(), 0500), 0);
    cases.push_back(
        {absl::StrCat(read_only, "/db"), true, absl::StatusCode::kUnavailable});
  }
  for (const Case& c : cases) {
    RocksDbStoreOptions options;
    options.path = c.path;
    options.create_if_missing = c.create_if_missing;
    absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
        OpenRocksDbStore(options);
    ASSERT_FALSE(store.ok()) << c.path;
    EXPECT_EQ(store.status().code(), c.code) << store.status();
    EXPECT_THAT(store.status().message(), HasSubstr(c.path));
  }
  EXPECT_EQ(OpenRocksDbStore(RocksDbStoreOptions{}).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST(RocksDbStoreTest, SecondOpenOfTheSameDatabaseFails) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  std::unique_ptr<engine::MemoryStore> first = OpenOrDie(path);
  ASSERT_NE(first, nullptr);
  RocksDbStoreOptions options;
  options.path = path;
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> second =
      OpenRocksDbStore(options);
  ASSERT_FALSE(second.ok());
  EXPECT_EQ(second.status().code(), absl::StatusCode::kUnavailable)
      << second.status();
  EXPECT_THAT(second.status().message(), HasSubstr("lock"));
}

// --- Records written behind the store's back.

// Writes raw key/value pairs into the (closed) database at `path`.
void PutRaw(const std::string& path,
            const std::vector<std::pair<std::string, std::string>>& records) {
  rocksdb::DB* raw = nullptr;
  rocksdb::Options options;
  ASSERT_TRUE(rocksdb::DB::Open(options, path, &raw).ok());
  std::unique_ptr<rocksdb::DB> db(raw);
  for (const auto& [key, value] : records) {
    ASSERT_TRUE(db->Put(rocksdb::WriteOptions(), key, value).ok());
  }
  ASSERT_TRUE(db->Close().ok());
}

// Deletes `keys` from the (closed) database at `path`.
void DeleteRaw(const std::string& path, const std::vector<std::string>& keys) {
  rocksdb::DB* raw = nullptr;
  ASSERT_TRUE(rocksdb::DB::Open(rocksdb::Options(), path, &raw).ok());
  std::unique_ptr<rocksdb::DB> db(raw);
  for (const std::string& key : keys) {
    ASSERT_TRUE(db->Delete(rocksdb::WriteOptions(), key).ok());
  }
  ASSERT_TRUE(db->Close().ok());
}

// Every key/value pair of the (closed) database at `path`.
std::map<std::string, std::string> ReadRaw(const std::string& path) {
  std::map<std::string, std::string> records;
  rocksdb::DB* raw = nullptr;
  EXPECT_TRUE(rocksdb::DB::Open(rocksdb::Options(), path, &raw).ok());
  std::unique_ptr<rocksdb::DB> db(raw);
  if (db == nullptr) return records;
  std::unique_ptr<rocksdb::Iterator> it(
      db->NewIterator(rocksdb::ReadOptions()));
  for (it->SeekToFirst(); it->Valid(); it->Next()) {
    records.emplace(it->key().ToString(), it->value().ToString());
  }
  it.reset();
  EXPECT_TRUE(db->Close().ok());
  return records;
}

bool HasTag(const std::string& key, keys::Tag tag) {
  return !key.empty() && key.front() == static_cast<char>(tag);
}

// Layout 2 (keys.h): a static-memory trace's record holds no code; its code
// is under a key of its own, one per trace, and goes with the trace.
TEST(RocksDbStoreTest, EveryStoredTraceHasOneCodeApartAndNoCodeOutlivesIt) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  size_t held = 0;
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    // Consolidations, replay updates, forgetting and single erasures.
    for (const FleetMutation& m : ScriptedMutations(60)) {
      ASSERT_TRUE(store->Apply("f", m).ok());
    }
    absl::StatusOr<FleetRecord> record = store->LoadFleet("f");
    ASSERT_TRUE(record.ok()) << record.status();
    for (const core::Cluster& cluster : record->clusters) {
      held += cluster.traces.size();
      for (const core::MemoryTrace& trace : cluster.traces) {
        EXPECT_FALSE(trace.code.empty()) << trace.robot_id << "/" << trace.seq;
      }
    }
  }
  ASSERT_GT(held, 3u);
  size_t records = 0;
  size_t codes = 0;
  for (const auto& [key, value] : ReadRaw(path)) {
    if (HasTag(key, keys::Tag::kTrace)) {
      ++records;
      absl::StatusOr<core::MemoryTrace> trace = DecodeTrace(key, value);
      ASSERT_TRUE(trace.ok()) << trace.status();
      EXPECT_TRUE(trace->code.empty()) << keys::Describe(key);
    }
    if (HasTag(key, keys::Tag::kCode)) ++codes;
  }
  EXPECT_EQ(records, held);
  EXPECT_EQ(codes, held);
}

TEST(RocksDbStoreTest, AnUpdateRewritesTheRecordAndKeepsTheStoredCode) {
  TempDir dir;
  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(dir.path());
  ASSERT_NE(store, nullptr);
  FleetMutation put;
  put.put_clusters = {testing::MakeCluster(1, "r", {1, 2})};
  ASSERT_TRUE(store->Apply("f", put).ok());
  for (bool held : {true, false}) {
    FleetMutation update;
    core::MemoryTrace changed = put.put_clusters[0].traces[1];
    changed.replay_count += held ? 5 : 7;
    changed.code.assign(changed.code.size(), 42.0f);  // never done: ignored
    update.update_traces = {changed};
    update.update_traces_held = held;
    ASSERT_TRUE(store->Apply("f", update).ok());
    absl::StatusOr<FleetRecord> record = store->LoadFleet("f");
    ASSERT_TRUE(record.ok()) << record.status();
    const core::MemoryTrace& loaded = record->clusters.at(0).traces.at(1);
    EXPECT_EQ(loaded.replay_count, changed.replay_count) << held;
    EXPECT_EQ(loaded.code, put.put_clusters[0].traces[1].code) << held;
  }
}

// What a build of layout 1 wrote: the codes inside the trace records, no
// code keys. `migrated_already` traces are left in layout 2 (a migration
// that a crash cut short).
void BackToLayoutOne(const std::string& path, size_t migrated_already) {
  std::vector<std::pair<std::string, std::string>> puts;
  std::vector<std::string> erased;
  const std::map<std::string, std::string> records = ReadRaw(path);
  size_t seen = 0;
  for (const auto& [key, value] : records) {
    if (!HasTag(key, keys::Tag::kTrace) || seen++ < migrated_already) continue;
    absl::StatusOr<core::MemoryTrace> trace = DecodeTrace(key, value);
    ASSERT_TRUE(trace.ok()) << trace.status();
    const std::optional<keys::ParsedKey> parsed = keys::Parse(key);
    ASSERT_TRUE(parsed.has_value());
    const std::string code_key = keys::CodeKey(parsed->fleet_id, trace->key());
    ASSERT_TRUE(records.contains(code_key)) << keys::Describe(code_key);
    ASSERT_TRUE(DecodeCode(code_key, records.at(code_key), &trace->code).ok());
    puts.emplace_back(key, EncodeTrace(*trace));
    erased.push_back(code_key);
  }
  puts.emplace_back(std::string(keys::kFormatKey),
                    std::string(keys::kFormatVersion1));
  DeleteRaw(path, erased);
  PutRaw(path, puts);
}

TEST(RocksDbStoreTest, AStoreOfLayoutOneIsMigratedWhereACrashLeftIt) {
  for (size_t migrated_already : {size_t{0}, size_t{3}}) {
    TempDir dir;
    const std::string path = absl::StrCat(dir.path(), "/db");
    std::vector<std::string> before;
    const std::vector<std::string> fleets = {"f", "f1"};
    {
      std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
      ASSERT_NE(store, nullptr);
      for (const std::string& fleet : fleets) {
        for (const FleetMutation& m : ScriptedMutations(40)) {
          ASSERT_TRUE(store->Apply(fleet, m).ok());
        }
        before.push_back(DumpFleet(*store, fleet));
      }
    }
    BackToLayoutOne(path, migrated_already);
    size_t codes_left = 0;
    for (const auto& [key, value] : ReadRaw(path)) {
      codes_left += HasTag(key, keys::Tag::kCode);
    }
    ASSERT_EQ(codes_left, migrated_already);
    for (int open = 0; open < 2; ++open) {  // migrated, then as it is
      std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
      ASSERT_NE(store, nullptr);
      for (size_t i = 0; i < fleets.size(); ++i) {
        EXPECT_EQ(DumpFleet(*store, fleets[i]), before[i])
            << fleets[i] << " open " << open << " " << migrated_already;
      }
    }
    const std::map<std::string, std::string> records = ReadRaw(path);
    EXPECT_EQ(records.at(std::string(keys::kFormatKey)), keys::kFormatVersion);
    size_t traces = 0;
    for (const auto& [key, value] : records) {
      if (!HasTag(key, keys::Tag::kTrace)) continue;
      ++traces;
      absl::StatusOr<core::MemoryTrace> trace = DecodeTrace(key, value);
      ASSERT_TRUE(trace.ok()) << trace.status();
      EXPECT_TRUE(trace->code.empty()) << keys::Describe(key);
      const std::optional<keys::ParsedKey> parsed = keys::Parse(key);
      EXPECT_TRUE(
          records.contains(keys::CodeKey(parsed->fleet_id, trace->key())));
    }
    EXPECT_GT(traces, 3u);
  }
}

class RocksDbCorruptionTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path_);
    ASSERT_NE(store, nullptr);
    FleetMutation m;
    m.put_clusters = {testing::MakeCluster(1, "r", {1, 2})};
    m.append_events = {
        testing::MakeEvent(1, core::EventType::kClusterAdded, 1)};
    ASSERT_TRUE(store->Apply("f", m).ok());
    ASSERT_TRUE(store->Apply("g", m).ok());
  }

  // Loads of "f" and of its events fail with DATA_LOSS naming `key`; "g" is
  // unaffected.
  void ExpectDataLoss(const std::string& what, bool in_events) {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path_);
    ASSERT_NE(store, nullptr);
    const absl::Status status = in_events
                                    ? store->ReadEvents("f", 0, 10).status()
                                    : store->LoadFleet("f").status();
    EXPECT_EQ(status.code(), absl::StatusCode::kDataLoss) << status;
    EXPECT_THAT(status.message(), HasSubstr(what));
    EXPECT_TRUE(store->LoadFleet("g").ok());
    EXPECT_TRUE(store->ReadEvents("g", 0, 10).ok());
  }

  TempDir dir_;
  const std::string path_ = absl::StrCat(dir_.path(), "/db");
};

TEST_F(RocksDbCorruptionTest, UnparsableTrace) {
  PutRaw(path_, {{keys::TraceKey("f", {"r", 2}), "\xff\xff\xff"}});
  ExpectDataLoss("trace[f/r/2]", false);
}

TEST_F(RocksDbCorruptionTest, UnparsableEvent) {
  PutRaw(path_, {{keys::EventKey("f", 1), "\xff"}});
  ExpectDataLoss("event[f/1]", true);
}

TEST_F(RocksDbCorruptionTest, RecordUnderAnotherKey) {
  core::MemoryTrace trace = testing::MakeTrace("r", 1);
  trace.cluster_id = 1;
  PutRaw(path_, {{keys::TraceKey("f", {"r", 2}), EncodeTrace(trace)}});
  ExpectDataLoss("trace[f/r/2]: trace does not match its key", false);
}

TEST_F(RocksDbCorruptionTest, TraceThatNoClusterLists) {
  core::MemoryTrace trace = testing::MakeTrace("r", 9);
  trace.cluster_id = 1;
  PutRaw(path_, {{keys::TraceKey("f", {"r", 9}), EncodeTrace(trace)}});
  ExpectDataLoss("trace[f/r/9]", false);
}

TEST_F(RocksDbCorruptionTest, ClusterMemberWithoutTrace) {
  PutRaw(path_, {{keys::ClusterKey("f", 2),
                  EncodeCluster(StoredCluster{2, "r", {1.0f}, {{"r", 7}}})}});
  ExpectDataLoss("cluster[f/2]", false);
}

TEST_F(RocksDbCorruptionTest, TraceWithoutItsCode) {
  DeleteRaw(path_, {keys::CodeKey("f", {"r", 2})});
  ExpectDataLoss("trace[f/r/2] has no code (code[f/r/2] is missing)", false);
}

TEST_F(RocksDbCorruptionTest, CodeOfPartialFloats) {
  PutRaw(path_, {{keys::CodeKey("f", {"r", 2}), "xyz"}});
  ExpectDataLoss("code[f/r/2]", false);
}

TEST_F(RocksDbCorruptionTest, OtherKeyLayoutVersionIsRefused) {
  PutRaw(path_, {{std::string(keys::kFormatKey), "fleetmem.storage/99"}});
  RocksDbStoreOptions options;
  options.path = path_;
  const absl::Status status = OpenRocksDbStore(options).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << status;
  EXPECT_THAT(status.message(), HasSubstr("fleetmem.storage/99"));
}

// Options for a store in `dir` with a 1 MiB disk reserve whose free space
// is what `free_bytes` holds.
RocksDbStoreOptions ReserveOptions(const testing::TempDir& dir,
                                   std::atomic<uint64_t>* free_bytes) {
  RocksDbStoreOptions options;
  options.path = dir.path();
  options.min_free_bytes = 1 << 20;
  options.free_bytes =
      [free_bytes](const std::string&) -> absl::StatusOr<uint64_t> {
    return free_bytes->load();
  };
  return options;
}

TEST(RocksDbStoreTest, BelowTheDiskReserveWritesAreRefusedAndReadsServed) {
  testing::TempDir dir;
  std::atomic<uint64_t> free_bytes{uint64_t{1} << 30};
  const RocksDbStoreOptions options = ReserveOptions(dir, &free_bytes);
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
      OpenRocksDbStore(options);
  ASSERT_TRUE(store.ok()) << store.status();
  const std::vector<engine::FleetMutation> script =
      testing::ScriptedMutations(3);
  ASSERT_TRUE((*store)->Apply("f", script[0]).ok());
  const std::string before = DumpFleet(**store, "f");

  free_bytes = (1 << 20) + 100;  // the reserve, plus less than a write needs
  const absl::Status refused = (*store)->Apply("f", script[1]);
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.message(), HasSubstr("disk nearly full"));
  EXPECT_THAT(refused.message(), HasSubstr("nothing was stored"));
  EXPECT_EQ(DumpFleet(**store, "f"), before) << "a refused write changed it";

  free_bytes = uint64_t{1} << 30;  // space returns
  EXPECT_TRUE((*store)->Apply("f", script[1]).ok());
  EXPECT_EQ(DumpFleet(**store, "f"), ReferenceDump(script, 2, "f"));
}

// An index snapshot stops at the disk reserve, leaves no partial file and
// keeps the earlier snapshot.
TEST(RocksDbStoreTest, IndexSnapshotStopsAtTheDiskReserve) {
  testing::TempDir dir;
  std::atomic<uint64_t> free_bytes{uint64_t{8} << 20};
  const RocksDbStoreOptions options = ReserveOptions(dir, &free_bytes);
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
      OpenRocksDbStore(options);
  ASSERT_TRUE(store.ok()) << store.status();
  ASSERT_TRUE((*store)
                  ->SaveIndexSnapshot("f1",
                                      [](core::ByteWriter& out) {
                                        out.PutString("earlier");
                                        return absl::OkStatus();
                                      })
                  .ok());
  // Each MiB written takes a MiB of the free space.
  const absl::Status status =
      (*store)->SaveIndexSnapshot("f1", [&](core::ByteWriter& out) {
        const std::string mib(1 << 20, 'x');
        for (int i = 0; i < 16; ++i) {
          out.PutBytes(mib.data(), mib.size());
          free_bytes -= mib.size();
        }
        return absl::OkStatus();
      });
  EXPECT_EQ(status.code(), absl::StatusCode::kResourceExhausted) << status;
  EXPECT_THAT(status.message(), HasSubstr("disk nearly full"));
  EXPECT_THAT(status.message(), HasSubstr("no index snapshot written"));
  const std::string directory = absl::StrCat(options.path, "/index-snapshots");
  EXPECT_EQ(std::distance(std::filesystem::directory_iterator(directory),
                          std::filesystem::directory_iterator()),
            1);  // the earlier one, no temporary file
  std::string earlier;
  ASSERT_TRUE((*store)
                  ->ReadIndexSnapshot(
                      "f1",
                      [&earlier](const engine::IndexSnapshotBytes& snapshot) {
                        core::ByteReader in(snapshot.bytes);
                        in.GetString(&earlier, 100);
                        return absl::OkStatus();
                      })
                  .ok());
  EXPECT_EQ(earlier, "earlier");
}

// A store in `dir`/db (options.path set to it).
absl::StatusOr<std::unique_ptr<engine::MemoryStore>> OpenInDb(
    const TempDir& dir, RocksDbStoreOptions& options) {
  options.path = absl::StrCat(dir.path(), "/db");
  return OpenRocksDbStore(options);
}

// A damaged index snapshot is refused and removed: its bytes are handed
// before the checksum is checked, whose verdict is DATA_LOSS, and so is the
// read's status whether the reader asked for the verdict or not; the store
// itself is untouched.
TEST(RocksDbStoreTest, DamagedIndexSnapshotIsDataLoss) {
  TempDir dir;
  RocksDbStoreOptions options;
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
      OpenInDb(dir, options);
  ASSERT_TRUE(store.ok()) << store.status();
  ASSERT_TRUE((*store)
                  ->SaveIndexSnapshot("f1",
                                      [](core::ByteWriter& out) {
                                        out.PutString(std::string(4096, 'a'));
                                        return absl::OkStatus();
                                      })
                  .ok());
  const std::string path =
      SnapshotFilePath(absl::StrCat(options.path, "/index-snapshots"), "f1");
  {
    std::fstream file(path, std::ios::in | std::ios::out | std::ios::binary);
    ASSERT_TRUE(file.is_open());
    file.seekp(1000);
    file.put('b');
  }
  const std::string damaged = [&] {
    std::ifstream file(path, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(file), {});
  }();
  for (const bool asks : {true, false}) {
    SCOPED_TRACE(asks ? "the reader checks" : "the reader does not check");
    {
      std::ofstream file(path, std::ios::binary | std::ios::trunc);
      file << damaged;  // back after the first read removed it
    }
    bool read = false;
    absl::Status verdict;
    absl::Status status = (*store)->ReadIndexSnapshot(
        "f1", [&](const engine::IndexSnapshotBytes& snapshot) {
          read = true;
          if (asks) {
            verdict = snapshot.check();
            EXPECT_EQ(snapshot.check(), verdict);  // once
          }
          return absl::OkStatus();
        });
    EXPECT_EQ(status.code(), absl::StatusCode::kDataLoss) << status;
    EXPECT_THAT(std::string(status.message()), HasSubstr("checksum"));
    EXPECT_TRUE(read);
    if (asks) EXPECT_EQ(verdict, status);
    EXPECT_FALSE(std::ifstream(path).is_open());
  }
}

// A snapshot's self-checked bytes (ByteWriter::PutSelfCheckedBytes) are
// left out of its file's checksum: a change there is handed to the reader
// (whose own checks find it), a change anywhere else, or to the list of
// those ranges, is DATA_LOSS. A file of the earlier frame (FMIDXSN1, every
// byte checked) is still read.
TEST(RocksDbStoreTest, SelfCheckedBytesAreLeftOutOfTheSnapshotsChecksum) {
  TempDir dir;
  RocksDbStoreOptions options;
  absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
      OpenInDb(dir, options);
  ASSERT_TRUE(store.ok()) << store.status();
  const std::string path =
      SnapshotFilePath(absl::StrCat(options.path, "/index-snapshots"), "f1");
  auto save = [&] {
    return (*store)->SaveIndexSnapshot("f1", [](core::ByteWriter& out) {
      out.PutString("head");
      out.PutSelfCheckedBytes(std::string(4096, 'x').data(), 4096);
      out.PutSelfCheckedBytes(std::string(100, 'y').data(), 100);
      out.PutString("tail");
      return absl::OkStatus();
    });
  };
  // The payload as read, or the read's status.
  auto read = [&]() -> absl::StatusOr<std::string> {
    std::string payload;
    absl::Status status = (*store)->ReadIndexSnapshot(
        "f1", [&](const engine::IndexSnapshotBytes& snapshot) {
          payload.assign(snapshot.bytes.begin(), snapshot.bytes.end());
          return snapshot.check();
        });
    if (!status.ok()) return status;
    return payload;
  };
  auto flip = [&](std::streamoff at) {
    std::fstream file(path, std::ios::in | std::ios::out | std::ios::binary);
    char byte = 0;
    file.seekg(at);
    file.get(byte);
    file.seekp(at);
    file.put(static_cast<char>(byte ^ 1));
    return file.good();
  };
  const std::streamoff payload_at = 16 + 8 + 2;  // after the key "f1"
  const std::streamoff self_checked_at = payload_at + 8 + 4;
  std::string expected = std::string("\x04\0\0\0\0\0\0\0head", 12) +
                         std::string(4096, 'x') + std::string(100, 'y') +
                         std::string("\x04\0\0\0\0\0\0\0tail", 12);

  ASSERT_TRUE(save().ok());
  ASSERT_EQ(read().value_or("not read"), expected);
  // One range (the two writes are adjacent), then the trailer.
  EXPECT_EQ(std::filesystem::file_size(path),
            payload_at + expected.size() + 16 + 8 + 16);
  ASSERT_TRUE(flip(self_checked_at + 4000));
  expected[12 + 4000] ^= 1;
  EXPECT_EQ(read().value_or("not read"), expected);
  for (const std::streamoff at :
       {payload_at + 9, self_checked_at + 4196 + 10,
        static_cast<std::streamoff>(payload_at + expected.size() + 3),
        static_cast<std::streamoff>(payload_at + expected.size() + 17)}) {
    SCOPED_TRACE(at);
    ASSERT_TRUE(save().ok());
    ASSERT_TRUE(flip(at));
    const absl::StatusOr<std::string> damaged = read();
    EXPECT_EQ(damaged.status().code(), absl::StatusCode::kDataLoss)
        << damaged.status();
    EXPECT_FALSE(std::filesystem::exists(path));
  }

  // FMIDXSN1: magic, stamp, key, payload, its size, XXH3 of all after the
  // magic.
  std::string whole = "FMIDXSN1";
  auto put = [&whole](uint64_t value) {
    whole.append(reinterpret_cast<const char*>(&value), sizeof(value));
  };
  put(7);
  put(2);
  whole += "f1";
  whole += "an earlier build's payload";
  const uint64_t digest = XXH3_64bits(whole.data() + 8, whole.size() - 8);
  put(26);
  put(digest);
  {
    std::ofstream file(path, std::ios::binary | std::ios::trunc);
    file << whole;
  }
  EXPECT_EQ(read().value_or("not read"), "an earlier build's payload");
}

// An index snapshot is current only while its mark names the file on disk
// and the store knows that nothing wrote behind it: a write by a build
// that keeps no marks (here: raw, after a clean close) makes every mark
// void at the next open, and they are deleted; a file that is not the one
// marked (put there by hand) is not current either.
TEST(RocksDbStoreTest, IndexSnapshotMarksDoNotOutliveAnUnknownWrite) {
  TempDir dir;
  const std::string path = absl::StrCat(dir.path(), "/db");
  const std::string snapshots = absl::StrCat(path, "/index-snapshots");
  auto save = [](engine::MemoryStore& store, std::string_view fleet,
                 std::string_view payload) {
    return store.SaveIndexSnapshot(fleet, [&](core::ByteWriter& out) {
      out.PutString(payload);
      return absl::OkStatus();
    });
  };
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    ASSERT_TRUE(save(*store, "f1", "one").ok());
    ASSERT_TRUE(save(*store, "f2", "two").ok());
  }
  // A copy of f2's file, to put back over a later one.
  std::filesystem::copy_file(SnapshotFilePath(snapshots, "f2"),
                             absl::StrCat(dir.path(), "/f2-old"));
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    EXPECT_TRUE(store->IndexSnapshotCurrent("f1"));
    ASSERT_TRUE(save(*store, "f2", "two, later").ok());
    EXPECT_TRUE(store->IndexSnapshotCurrent("f2"));
    std::filesystem::copy_file(
        absl::StrCat(dir.path(), "/f2-old"), SnapshotFilePath(snapshots, "f2"),
        std::filesystem::copy_options::overwrite_existing);
    EXPECT_FALSE(store->IndexSnapshotCurrent("f2"));
  }
  PutRaw(path, {{keys::RobotKey("f3", "r1"), "written by an older build"}});
  {
    std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
    ASSERT_NE(store, nullptr);
    EXPECT_FALSE(store->IndexSnapshotCurrent("f1"));
  }
  for (const auto& [key, value] : ReadRaw(path)) {
    EXPECT_NE(key.front(), static_cast<char>(keys::Tag::kSnapshotMark))
        << keys::Describe(key);
  }
  // The next save marks again.
  std::unique_ptr<engine::MemoryStore> store = OpenOrDie(path);
  ASSERT_NE(store, nullptr);
  ASSERT_TRUE(save(*store, "f1", "one, again").ok());
  EXPECT_TRUE(store->IndexSnapshotCurrent("f1"));
}

}  // namespace
}  // namespace fleetmem::storage
