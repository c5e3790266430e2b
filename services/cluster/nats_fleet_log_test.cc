// NatsFleetLog against a real nats-server with JetStream (Debian's), started
// on a random loopback port in a temporary store directory.
#include "services/cluster/nats_fleet_log.h"

#include <chrono>
#include <iostream>
#include <memory>
#include <optional>
#include <string>
#include <thread>
#include <tuple>
#include <variant>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/cluster/testing/nats_fixture.h"
#include "tests/server_process.h"

namespace fleetmem::cluster {
namespace {

using ::testing::HasSubstr;
using testing::NatsServerOptions;
using testing::ServerOptions;

using NatsFleetLogTest = NatsFixture;

// Appends a SampleReplay call naming `robot` (a record that carries any
// bytes) under `id`.
absl::StatusOr<engine::AppendedEntry> AppendCall(NatsFleetLog& log,
                                                 const std::string& fleet,
                                                 const std::string& id,
                                                 const std::string& robot) {
  const engine::LogAppend append{engine::SampleReplayRecord{robot, 1, ""}, id};
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log.Append(fleet, {&append, 1}, {});
  if (!appended.ok()) return appended.status();
  return appended->front();
}

std::string RobotOf(const engine::LogEntry& entry) {
  const auto* call = std::get_if<engine::SampleReplayCall>(&entry.record);
  return call == nullptr ? "(not a call)" : call->robot_id;
}

TEST_F(NatsFleetLogTest, AppendsInOrderAndDropsARepeatedId) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  const std::string fleet = "city fleet/1.a*";  // not a NATS token
  for (const auto& [id, data, sequence] :
       std::vector<std::tuple<std::string, std::string, uint64_t>>{
           {"r1:1-100", "first", 1},
           {"r2:1-50", std::string("with\0zero", 9), 2},
           {"r1:101-200", "third", 3}}) {
    absl::StatusOr<engine::AppendedEntry> appended =
        AppendCall(*log, fleet, id, data);
    ASSERT_TRUE(appended.ok()) << appended.status();
    EXPECT_EQ(appended->sequence, sequence);
    EXPECT_FALSE(appended->duplicate);
  }
  // The same id again (a retried upload): not stored twice.
  absl::StatusOr<engine::AppendedEntry> again =
      AppendCall(*log, fleet, "r2:1-50", "retried");
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_TRUE(again->duplicate);
  EXPECT_EQ(again->sequence, 2u);
  EXPECT_EQ(log->Bounds(fleet)->last, 3u);

  absl::StatusOr<std::vector<engine::LogEntry>> all = log->Read(fleet, 0, 100);
  ASSERT_TRUE(all.ok()) << all.status();
  ASSERT_EQ(all->size(), 3u);
  EXPECT_EQ((*all)[1].sequence, 2u);
  EXPECT_EQ((*all)[1].id, "r2:1-50");
  EXPECT_EQ(RobotOf((*all)[1]), std::string("with\0zero", 9));
  absl::StatusOr<std::vector<engine::LogEntry>> one = log->Read(fleet, 2, 1);
  ASSERT_TRUE(one.ok()) << one.status();
  ASSERT_EQ(one->size(), 1u);
  EXPECT_EQ(RobotOf(one->front()), "third");
  EXPECT_TRUE(log->Read(fleet, 3, 10)->empty());
  // No id: no deduplication (a call's entry).
  EXPECT_EQ(AppendCall(*log, fleet, "", "x")->sequence, 4u);
  EXPECT_EQ(AppendCall(*log, fleet, "", "x")->sequence, 5u);
  // JetStream numbers its entries itself.
  const engine::LogAppend floor{engine::ConsolidateRecord{}};
  EXPECT_EQ(log->Append(fleet, {&floor, 1}, {.above = 10}).status().code(),
            absl::StatusCode::kInvalidArgument);

  // Each fleet has its own log; a fleet without one reads as empty.
  EXPECT_EQ(AppendCall(*log, "other", "r1:1-100", "x")->sequence, 1u);
  EXPECT_EQ(log->Bounds("never written")->last, 0u);
  EXPECT_TRUE(log->Read("never written", 0, 10)->empty());
}

// Several entries in one Append (a write path's group) are published
// without waiting for each acknowledgement: numbered in order, each
// deduplicated by its id, several appends at once (other fleets') keep
// their own outcomes; only_first holds for the first.
TEST_F(NatsFleetLogTest, SeveralEntriesArePipelinedInOrder) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  auto group = [](const std::string& prefix, int count) {
    std::vector<std::string> robots;
    for (int i = 0; i < count; ++i) robots.push_back(absl::StrCat(prefix, i));
    return robots;
  };
  auto append = [&](const std::string& fleet,
                    const std::vector<std::string>& robots,
                    engine::AppendOptions options = {}) {
    std::vector<engine::LogAppend> appends;
    for (const std::string& robot : robots) {
      appends.push_back({engine::SampleReplayRecord{robot, 1, ""}, robot});
    }
    return log->Append(fleet, appends, options);
  };
  absl::StatusOr<std::vector<engine::AppendedEntry>> first =
      append("p", group("a", 20), {.only_first = true});
  ASSERT_TRUE(first.ok()) << first.status();
  ASSERT_EQ(first->size(), 20u);
  for (size_t i = 0; i < first->size(); ++i) {
    EXPECT_EQ((*first)[i].sequence, i + 1);
    EXPECT_FALSE((*first)[i].duplicate);
  }
  // Half of them again, and new ones: the repeated ids are duplicates of
  // the entries that hold them.
  std::vector<std::string> mixed = group("a", 10);
  for (const std::string& robot : group("b", 10)) mixed.push_back(robot);
  absl::StatusOr<std::vector<engine::AppendedEntry>> again = append("p", mixed);
  ASSERT_TRUE(again.ok()) << again.status();
  for (size_t i = 0; i < 10; ++i) {
    EXPECT_TRUE((*again)[i].duplicate);
    EXPECT_EQ((*again)[i].sequence, i + 1);
    EXPECT_FALSE((*again)[10 + i].duplicate);
    EXPECT_EQ((*again)[10 + i].sequence, 21 + i);
  }
  absl::StatusOr<std::vector<engine::LogEntry>> all = log->Read("p", 0, 100);
  ASSERT_TRUE(all.ok()) << all.status();
  ASSERT_EQ(all->size(), 30u);
  EXPECT_EQ(RobotOf((*all)[0]), "a0");
  EXPECT_EQ(RobotOf((*all)[29]), "b9");
  // The log holds entries: only_first refuses the whole group.
  EXPECT_EQ(append("p", group("c", 3), {.only_first = true}).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ(log->Bounds("p")->last, 30u);

  // Four fleets' groups at once, on one connection.
  std::vector<std::thread> writers;
  std::vector<absl::StatusOr<std::vector<engine::AppendedEntry>>> outcomes(
      4, absl::UnknownError("not run"));
  for (int f = 0; f < 4; ++f) {
    writers.emplace_back(
        [&, f] { outcomes[f] = append(absl::StrCat("q", f), group("r", 25)); });
  }
  for (std::thread& writer : writers) writer.join();
  for (int f = 0; f < 4; ++f) {
    ASSERT_TRUE(outcomes[f].ok()) << outcomes[f].status();
    ASSERT_EQ(outcomes[f]->size(), 25u);
    EXPECT_EQ(outcomes[f]->back().sequence, 25u);
  }
}

// Every kind of record reads back as it was appended; `only_first` appends
// only to an empty log.
TEST_F(NatsFleetLogTest, RecordsReadBackAsAppended) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  std::vector<core::MemoryTrace> traces(2);
  for (uint64_t i = 0; i < traces.size(); ++i) {
    traces[i].robot_id = "r1";
    traces[i].seq = i + 1;
    traces[i].code = {0.5f, -1.0f, static_cast<float>(i)};
    traces[i].place = {1.0, 2.0, 0.0, 0.25};
    traces[i].encoder_version = "enc-v1";
  }
  const std::vector<engine::LogAppend> appends = {
      {engine::UploadRecord{traces}, "upload/2/r1/1-2"},
      {engine::ConsolidateRecord{}},
      {engine::SampleReplayRecord{"r1", 7, "req-1"}}};
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log->Append("f", appends, {.only_first = true});
  ASSERT_TRUE(appended.ok()) << appended.status();
  ASSERT_EQ(appended->size(), 3u);
  EXPECT_EQ((*appended)[2].sequence, 3u);
  // Another upload creating the fleet: refused. (The same first entry
  // again is a retry: answered as a duplicate, as without the option.)
  const engine::LogAppend other{engine::UploadRecord{traces}, "other"};
  EXPECT_EQ(log->Append("f", {&other, 1}, {.only_first = true}).status().code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_TRUE(log->Append("f", {&appends[0], 1}, {.only_first = true})
                  ->front()
                  .duplicate);
  EXPECT_EQ(log->Bounds("f")->last, 3u);

  absl::StatusOr<std::vector<engine::LogEntry>> all = log->Read("f", 0, 10);
  ASSERT_TRUE(all.ok()) << all.status();
  ASSERT_EQ(all->size(), 3u);
  ASSERT_EQ((*all)[0].traces().size(), 2u);
  EXPECT_EQ((*all)[0].traces()[1].code, traces[1].code);
  EXPECT_EQ((*all)[0].traces()[1].seq, 2u);
  EXPECT_TRUE(
      std::holds_alternative<engine::ConsolidateRecord>((*all)[1].record));
  const auto* call = std::get_if<engine::SampleReplayCall>(&(*all)[2].record);
  ASSERT_NE(call, nullptr);
  EXPECT_EQ(call->robot_id, "r1");
  EXPECT_EQ(call->count, 7u);
  EXPECT_EQ(call->request_id, "req-1");
  // Trimmed through 2: the bounds say so, and a read from before it is
  // OUT_OF_RANGE (a snapshot holds those entries).
  ASSERT_TRUE(log->Trim("f", 2).ok());
  EXPECT_EQ(log->Bounds("f")->first, 3u);
  EXPECT_EQ(log->Read("f", 0, 10).status().code(),
            absl::StatusCode::kOutOfRange);
  EXPECT_EQ(log->Read("f", 2, 10)->size(), 1u);
}

TEST_F(NatsFleetLogTest, AnEntryAboveNatsMaxPayloadIsRefusedClearly) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  absl::StatusOr<engine::AppendedEntry> big =
      AppendCall(*log, "f", "r:1", std::string(2 * 1024 * 1024, 'x'));
  EXPECT_EQ(big.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(big.status().message(), HasSubstr("max_payload"));
  EXPECT_EQ(log->Bounds("f")->last, 0u);
}

// Acknowledged entries survive nats-server being killed: a client of the
// restarted server (same store, same port) reads them all.
TEST_F(NatsFleetLogTest, AcknowledgedEntriesSurviveAKilledServer) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  for (int i = 1; i <= 50; ++i) {
    ASSERT_TRUE(
        AppendCall(*log, "f", absl::StrCat("r:", i), absl::StrCat(i)).ok());
  }
  const int port = nats_->port();
  log.reset();
  nats_->Kill();
  ServerOptions options =
      NatsServerOptions(dir_.Join("jetstream"), dir_.Join("nats.log"));
  options.extra_args[3] = absl::StrCat(port);  // "-p", PORT
  StartNats(options);
  log = Connect();
  ASSERT_NE(log, nullptr);
  absl::StatusOr<std::vector<engine::LogEntry>> all = log->Read("f", 0, 100);
  ASSERT_TRUE(all.ok()) << all.status();
  ASSERT_EQ(all->size(), 50u);
  for (int i = 0; i < 50; ++i)
    EXPECT_EQ(RobotOf((*all)[i]), absl::StrCat(i + 1));
}

// A group appended while NATS is gone fails, saying how many of its
// entries the log holds (none here).
TEST_F(NatsFleetLogTest, AGroupThatCannotBeAppendedSaysWhatTheLogHolds) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  ASSERT_TRUE(AppendCall(*log, "g", "r:0", "0").ok());  // its stream
  nats_->Kill();
  const std::vector<std::string> ids = {"r:1", "r:2", "r:3"};
  std::vector<engine::LogAppend> appends;
  for (const std::string& id : ids) {
    appends.push_back({engine::ConsolidateRecord{}, id});
  }
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log->Append("g", appends, {});
  ASSERT_FALSE(appended.ok());
  EXPECT_THAT(appended.status().message(),
              HasSubstr("the log holds 0 of these 3 entries"));
}

// Waits up to 5 s for `table` to resolve `alias` as `want` (nullopt: no
// alias).
bool Sees(const engine::AliasTable& table, const std::string& alias,
          const std::optional<std::string>& want) {
  for (int i = 0; i < 500; ++i) {
    if (table.Resolve(alias) == want) return true;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return false;
}

TEST_F(NatsFleetLogTest, AliasesAreSharedByEveryReplica) {
  std::unique_ptr<NatsFleetLog> a = Connect();
  std::unique_ptr<NatsFleetLog> b = Connect();
  ASSERT_NE(a, nullptr);
  ASSERT_NE(b, nullptr);
  ASSERT_TRUE(a->aliases().Create("live", "fleet:v1").ok());
  EXPECT_EQ(a->aliases().Resolve("live"), "fleet:v1");  // at once, here
  EXPECT_TRUE(Sees(b->aliases(), "live", "fleet:v1"));
  const absl::Status twice = b->aliases().Create("live", "fleet:v2");
  EXPECT_TRUE(absl::IsAlreadyExists(twice)) << twice;

  absl::StatusOr<std::string> before = b->aliases().Switch("live", "fleet:v2");
  ASSERT_TRUE(before.ok()) << before.status();
  EXPECT_EQ(*before, "fleet:v1");
  EXPECT_TRUE(Sees(a->aliases(), "live", "fleet:v2"));
  EXPECT_TRUE(absl::IsNotFound(a->aliases().Switch("nope", "x").status()));

  // A replica that connects later reads them when it connects.
  ASSERT_TRUE(a->aliases().Create("other", "fleet:v1").ok());
  std::unique_ptr<NatsFleetLog> c = Connect();
  ASSERT_NE(c, nullptr);
  EXPECT_TRUE(Sees(c->aliases(), "other", "fleet:v1"));
  absl::StatusOr<std::vector<engine::FleetAlias>> listed = c->aliases().List();
  ASSERT_TRUE(listed.ok()) << listed.status();
  ASSERT_EQ(listed->size(), 2u);
  EXPECT_EQ((*listed)[0].alias, "live");
  EXPECT_EQ((*listed)[0].fleet_id, "fleet:v2");

  absl::StatusOr<std::string> deleted = c->aliases().Delete("live");
  ASSERT_TRUE(deleted.ok()) << deleted.status();
  EXPECT_EQ(*deleted, "fleet:v2");
  EXPECT_TRUE(Sees(a->aliases(), "live", std::nullopt));
  EXPECT_TRUE(Sees(b->aliases(), "live", std::nullopt));
  EXPECT_TRUE(absl::IsNotFound(b->aliases().Delete("live").status()));
}

TEST_F(NatsFleetLogTest, ALeaseHasOneHolderAndFencesALateOne) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  absl::StatusOr<Lease> a = log->Acquire("f", "replica-a");
  ASSERT_TRUE(a.ok()) << a.status();
  absl::StatusOr<Lease> b = log->Acquire("f", "replica-b");
  EXPECT_EQ(b.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(b.status().message(), HasSubstr("replica-a"));

  // The same replica again (restarted): it takes its lease back at once,
  // and the lease its earlier run held is fenced.
  absl::StatusOr<Lease> again = log->Acquire("f", "replica-a");
  ASSERT_TRUE(again.ok()) << again.status();
  EXPECT_GT(again->revision, a->revision);
  EXPECT_EQ(log->Renew(*a).status().code(),
            absl::StatusCode::kFailedPrecondition);
  a = again;

  absl::StatusOr<Lease> renewed = log->Renew(*a);
  ASSERT_TRUE(renewed.ok()) << renewed.status();
  EXPECT_GT(renewed->revision, a->revision);
  // The revision it held before is stale: a second renewal from it fails.
  EXPECT_EQ(log->Renew(*a).status().code(),
            absl::StatusCode::kFailedPrecondition);
  absl::StatusOr<std::optional<Lease>> holder = log->Holder("f");
  ASSERT_TRUE(holder.ok() && holder->has_value());
  EXPECT_EQ((*holder)->owner, "replica-a");
  EXPECT_EQ((*holder)->revision, renewed->revision);

  ASSERT_TRUE(log->Release(*renewed).ok());
  EXPECT_FALSE(log->Holder("f")->has_value());
  b = log->Acquire("f", "replica-b");
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_GT(b->revision, renewed->revision);
  // A late release from the old holder does not drop the new one's lease.
  EXPECT_EQ(log->Release(*renewed).code(),
            absl::StatusCode::kFailedPrecondition);
  EXPECT_EQ((*log->Holder("f"))->owner, "replica-b");
  EXPECT_FALSE(log->Holder("another fleet")->has_value());
}

TEST_F(NatsFleetLogTest, ALeaseNotRenewedExpiresAndAnotherReplicaTakesIt) {
  std::unique_ptr<NatsFleetLog> log = Connect();
  ASSERT_NE(log, nullptr);
  absl::StatusOr<Lease> a = log->Acquire("f", "replica-a");
  ASSERT_TRUE(a.ok()) << a.status();
  // lease_ttl is 1 s here.
  const auto start = std::chrono::steady_clock::now();
  absl::StatusOr<Lease> b = log->Acquire("f", "replica-b");
  while (!b.ok() &&
         std::chrono::steady_clock::now() - start < std::chrono::seconds(10)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
    b = log->Acquire("f", "replica-b");
  }
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_GE(std::chrono::steady_clock::now() - start,
            std::chrono::milliseconds(900));
  EXPECT_GT(b->revision, a->revision);
  EXPECT_EQ(log->Renew(*a).status().code(),
            absl::StatusCode::kFailedPrecondition);
}

// Three nats-servers in one JetStream cluster (three copies of the lease
// bucket), and a lease client per replica.
class NatsClusterLeaseTest : public ::testing::Test {
 protected:
  void SetUp() override {
    for (ServerOptions& options : testing::NatsClusterOptions(dir_.path(), 3)) {
      nats_.push_back(std::make_unique<testing::ServerProcess>(options));
    }
    for (auto& nats : nats_) {
      absl::Status started = nats->Start();
      ASSERT_TRUE(started.ok()) << started;
    }
  }

  std::unique_ptr<NatsFleetLog> Connect() {
    NatsOptions options;
    for (auto& nats : nats_) {
      options.servers.push_back(absl::StrCat("nats://", nats->address()));
    }
    options.replicas = 3;
    options.lease_ttl = absl::Seconds(1);
    options.timeout = absl::Seconds(2);
    absl::StatusOr<std::unique_ptr<NatsFleetLog>> log =
        NatsFleetLog::Connect(options);
    // The cluster elects its meta leader after the servers start.
    for (int i = 0; i < 50 && !log.ok(); ++i) {
      std::this_thread::sleep_for(std::chrono::milliseconds(200));
      log = NatsFleetLog::Connect(options);
    }
    EXPECT_TRUE(log.ok()) << log.status();
    return log.ok() ? *std::move(log) : nullptr;
  }

  // Seconds from the moment replica-a takes `fleet` (and stops renewing)
  // until replica-b takes it, asking every 50 ms; -1 if not in 20 s.
  static double Takeover(NatsFleetLog& a, NatsFleetLog& b,
                         const std::string& fleet) {
    using Clock = std::chrono::steady_clock;
    auto start = Clock::now();
    while (!a.Acquire(fleet, "replica-a").ok()) {  // a leader election
      if (Clock::now() - start > std::chrono::seconds(20)) return -1;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    start = Clock::now();
    while (!b.Acquire(fleet, "replica-b").ok()) {
      if (Clock::now() - start > std::chrono::seconds(20)) return -1;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return std::chrono::duration<double>(Clock::now() - start).count();
  }

  testing::TempDir dir_{"fleetmem-nats-cluster-"};
  std::vector<std::unique_ptr<testing::ServerProcess>> nats_;
};

// A lease whose holder stopped renewing moves within two TTLs, also once
// JetStream has lost a server (the lease bucket's leader, or not) and
// elected new leaders: JetStream expires the key on time (measured for the
// paused-owner case, docs/distributed.md).
TEST_F(NatsClusterLeaseTest, ALeaseNotRenewedMovesWithinTwoTtls) {
  std::unique_ptr<NatsFleetLog> a = Connect();
  std::unique_ptr<NatsFleetLog> b = Connect();
  ASSERT_TRUE(a != nullptr && b != nullptr);
  std::vector<double> before;
  std::vector<double> after;
  for (int i = 0; i < 2; ++i) {
    before.push_back(Takeover(*a, *b, absl::StrCat("before-", i)));
  }
  nats_[1]->Kill();
  for (int i = 0; i < 4; ++i) {
    after.push_back(Takeover(*a, *b, absl::StrCat("after-", i)));
  }
  std::cout << "takeover (s), 3 servers: " << absl::StrJoin(before, " ")
            << "\ntakeover (s), one server killed: "
            << absl::StrJoin(after, " ") << "\n";
  for (const double seconds : before) {
    EXPECT_GE(seconds, 0.9);
    EXPECT_LT(seconds, 2.0);
  }
  for (const double seconds : after) {
    EXPECT_GE(seconds, 0.9);
    EXPECT_LT(seconds, 2.0);
  }
}

TEST(NatsFleetLogOptionsTest, BadOptionsAndNoServerAreClearErrors) {
  NatsOptions options;
  EXPECT_EQ(NatsFleetLog::Connect(options).status().code(),
            absl::StatusCode::kInvalidArgument);
  options.servers = {"nats://127.0.0.1:1"};
  options.replicas = 0;
  EXPECT_EQ(NatsFleetLog::Connect(options).status().code(),
            absl::StatusCode::kInvalidArgument);
  options.replicas = 1;
  options.cert_file = "client.pem";
  EXPECT_EQ(NatsFleetLog::Connect(options).status().code(),
            absl::StatusCode::kInvalidArgument);
  options.cert_file.clear();
  options.timeout = absl::Milliseconds(500);
  absl::StatusOr<std::unique_ptr<NatsFleetLog>> none =
      NatsFleetLog::Connect(options);
  EXPECT_EQ(none.status().code(), absl::StatusCode::kUnavailable)
      << none.status();
  EXPECT_THAT(none.status().message(), HasSubstr("127.0.0.1:1"));
}

}  // namespace
}  // namespace fleetmem::cluster
