// Distributed mode end to end (docs/distributed.md): three real
// fleetmem-server replicas on one real nats-server with JetStream, each on
// its own data dir. Uploads go to any replica; every fleet is owned and
// served by one; the loss of an owner (kill -9) hands its fleets to the
// others within the lease, with nothing lost or counted twice; and a replica
// that rebuilds the fleets from the log alone reaches the same memory.
#include <netinet/in.h>
#include <signal.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "absl/cleanup/cleanup.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
#include "tests/server_process.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

using Clock = std::chrono::steady_clock;

constexpr int kFleets = 4;
constexpr int kRobots = 2;
constexpr size_t kTraces = 250;  // per robot: one segment and a pending part

std::string FleetId(int fleet) { return absl::StrCat("fleet-", fleet); }
std::string RobotId(int robot) { return absl::StrCat("robot-", robot); }

TraceSpec Spec(int fleet, int robot, uint64_t first_seq, size_t count) {
  TraceSpec spec;
  spec.robot_id = RobotId(robot);
  spec.first_seq = first_seq;
  spec.count = count;
  spec.seed = 100 + fleet;
  return spec;
}

// The body of GET /metrics on the HTTP port (plain HTTP/1.0), or "".
std::string Metrics(int port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  address.sin_port = htons(static_cast<uint16_t>(port));
  std::string text;
  if (connect(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) ==
      0) {
    const std::string request = "GET /metrics HTTP/1.0\r\n\r\n";
    if (write(fd, request.data(), request.size()) ==
        static_cast<ssize_t>(request.size())) {
      char buffer[4096];
      ssize_t n;
      while ((n = read(fd, buffer, sizeof(buffer))) > 0) text.append(buffer, n);
    }
  }
  close(fd);
  const size_t body = text.find("\r\n\r\n");
  return body == std::string::npos ? "" : text.substr(body + 4);
}

// fleet -> value of each `name{fleet="..."} value` line of `text`.
std::map<std::string, double> FleetGauge(const std::string& text,
                                         const std::string& name) {
  std::map<std::string, double> values;
  const std::string prefix = name + "{fleet=\"";
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    if (!absl::StartsWith(line, prefix)) continue;
    line.remove_prefix(prefix.size());
    const size_t quote = line.find('"');
    const size_t space = line.rfind(' ');
    double value = 0;
    if (quote == absl::string_view::npos || space == absl::string_view::npos ||
        !absl::SimpleAtod(line.substr(space + 1), &value)) {
      continue;
    }
    values[std::string(line.substr(0, quote))] = value;
  }
  return values;
}

uint64_t Received(const v1::GetStatsResponse& stats) {
  uint64_t received = 0;
  for (const v1::RobotStats& robot : stats.robots()) {
    received += robot.received();
  }
  return received;
}

// Every trace of a fleet as "robot/seq cluster replay", for comparing two
// replicas' memories.
std::vector<std::string> Listing(v1::MemoryService::Stub& stub,
                                 const std::string& fleet_id,
                                 grpc::Status* status) {
  std::vector<std::string> lines;
  std::string token;
  do {
    v1::ListTracesRequest request;
    request.set_fleet_id(fleet_id);
    request.set_page_size(10000);
    request.set_page_token(token);
    v1::ListTracesResponse response;
    *status = stub.ListTraces(MakeContext().get(), request, &response);
    if (!status->ok()) return {};
    for (const v1::MemoryTrace& trace : response.traces()) {
      lines.push_back(absl::StrCat(trace.robot_id(), "/", trace.seq(), " ",
                                   trace.cluster_id(), " ",
                                   trace.replay_count()));
    }
    token = response.next_page_token();
  } while (!token.empty());
  return lines;
}

class ClusterIntegrationTest : public ::testing::Test {
 protected:
  void SetUp() override { ASSERT_FALSE(dir_.path().empty()); }

  // One nats-server with JetStream: one copy of each log.
  void StartNats() {
    nats_.push_back(std::make_unique<ServerProcess>(
        NatsServerOptions(dir_.Join("jetstream"), dir_.Join("nats.log"))));
    absl::Status started = nats_.back()->Start();
    ASSERT_TRUE(started.ok()) << started;
    nats_urls_ = absl::StrCat("nats://", nats_.back()->address());
  }

  // A JetStream cluster of three nats-servers routed to each other on
  // loopback: three copies of each log, a quorum of two.
  void StartNatsCluster() {
    for (ServerOptions& options : NatsClusterOptions(dir_.path(), 3)) {
      nats_.push_back(std::make_unique<ServerProcess>(std::move(options)));
    }
    // Each waits for its routes only after it listens: start all, then
    // wait for each.
    for (auto& nats : nats_) {
      absl::Status started = nats->Start();
      ASSERT_TRUE(started.ok()) << started;
    }
    nats_urls_.clear();
    for (auto& nats : nats_) {
      absl::StrAppend(&nats_urls_, nats_urls_.empty() ? "" : ",", "nats://",
                      nats->address());
    }
  }

  void TearDown() override {
    if (!HasFailure()) return;
    for (size_t i = 0; i < replicas_.size(); ++i) {
      std::cerr << "---- replica " << i << " ----\n"
                << ReadFileOrEmpty(
                       dir_.Join(absl::StrCat("replica-", i, ".log")))
                << "\n";
    }
    // What NATS said (a stream that stops answering: docs/distributed.md,
    // "The owner-loss case").
    for (const std::string& name :
         {std::string("nats.log"), std::string("nats-0.log"),
          std::string("nats-1.log"), std::string("nats-2.log")}) {
      const std::string text = ReadFileOrEmpty(dir_.Join(name));
      if (text.empty()) continue;
      std::cerr << "---- " << name << " (last 8000 bytes) ----\n"
                << text.substr(text.size() > 8000 ? text.size() - 8000 : 0)
                << "\n";
    }
  }

  // Starts replica `i` (a new one when i == replicas_.size()) on its own
  // data dir and a fixed port; leases of 1 s, rounds of 100 ms, a copy of
  // each log on each NATS server (at most three).
  void StartReplica(size_t i) {
    if (i == replicas_.size()) {
      replicas_.emplace_back();
      const std::vector<int> ports = FreePorts(2);
      ports_.push_back(ports[0]);
      http_ports_.push_back(ports[1]);
    }
    const std::string data = dir_.Join(absl::StrCat("replica-", i));
    std::filesystem::create_directories(data);
    const std::string config = dir_.Join(absl::StrCat("replica-", i, ".cfg"));
    std::ofstream out(config);
    out << "cluster { ";
    for (absl::string_view url : absl::StrSplit(nats_urls_, ',')) {
      out << "servers: \"" << url << "\" ";
    }
    out << "advertise: \"127.0.0.1:" << ports_[i]
        << "\" replicas: " << (nats_.size() >= 3 ? 3 : 1)
        << " lease_ttl_ms: 1000 round_interval_ms: 100"
        << " snapshot_every_entries: " << snapshot_every_ << " }\n"
        << extra_config_ << "\n";
    out.close();
    ServerOptions options;
    options.data_dir = data;
    options.config_file = config;
    options.listen = absl::StrCat("127.0.0.1:", ports_[i]);
    // Debug: each entry a replica applies is logged, and the logs are
    // printed when a case fails (an owner that once held fewer traces than
    // were acknowledged is not explained yet: docs/distributed.md).
    options.extra_args = {"--http-listen",
                          absl::StrCat("127.0.0.1:", http_ports_[i]),
                          "--log-level", "debug"};
    options.log_file = dir_.Join(absl::StrCat("replica-", i, ".log"));
    // A JetStream cluster elects its leaders some seconds after it listens;
    // the replica waits for it before it listens (longer on a loaded
    // machine, under a sanitizer).
    options.start_timeout = std::chrono::milliseconds(120000);
    replicas_[i] = std::make_unique<ServerProcess>(options);
    absl::Status started = replicas_[i]->Start();
    ASSERT_TRUE(started.ok()) << started;
  }

  std::unique_ptr<v1::MemoryService::Stub> Stub(size_t i) {
    return MakeStub(absl::StrCat("127.0.0.1:", ports_[i]));
  }

  // Uploads through replica `via`, retrying a failed stream (the ids
  // repeat, so a retry adds nothing twice) for up to 20 s.
  v1::UploadTracesResponse UploadVia(size_t via, int fleet, int robot,
                                     uint64_t first_seq, size_t count) {
    const std::vector<v1::MemoryTrace> traces =
        MakeTraces(Spec(fleet, robot, first_seq, count));
    const auto deadline = Clock::now() + std::chrono::seconds(20);
    Reply<v1::UploadTracesResponse> reply;
    do {
      reply = UploadTraces(*Stub(via), FleetId(fleet), traces, 100);
      if (reply.ok()) return reply.response;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    } while (Clock::now() < deadline);
    ADD_FAILURE() << "upload via replica " << via << ": "
                  << Describe(reply.status);
    return {};
  }

  // Polls GetStats through replica `via` until the fleet has received
  // `traces` (with `unacknowledged`, up to that many more: an upload stored
  // whose answer did not reach its robot before it stopped); the time it
  // took, or nullopt after `timeout`.
  std::optional<double> WaitForTraces(size_t via, int fleet, uint64_t traces,
                                      std::chrono::seconds timeout,
                                      uint64_t unacknowledged = 0) {
    const auto start = Clock::now();
    Reply<v1::GetStatsResponse> stats;
    do {
      stats = GetStats(*Stub(via), FleetId(fleet));
      if (stats.ok() && Received(stats.response) >= traces &&
          Received(stats.response) <= traces + unacknowledged) {
        return std::chrono::duration<double>(Clock::now() - start).count();
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    } while (Clock::now() - start < timeout);
    std::string robots;  // which seqs are missing: each robot's highest
    for (const v1::RobotStats& robot : stats.response.robots()) {
      absl::StrAppend(&robots, " ", robot.robot_id(), ": ", robot.received(),
                      " received, highest seq ", robot.max_seq(), ";");
    }
    ADD_FAILURE() << FleetId(fleet) << " via replica " << via << ": "
                  << (stats.ok() ? absl::StrCat(Received(stats.response),
                                                " traces, not ", traces, " (",
                                                robots, ")")
                                 : Describe(stats.status));
    return std::nullopt;
  }

  // Fleet id -> the address of its owner, from ListFleets through `via`.
  // `must_answer`: a failed call fails the test (else it lists nothing).
  std::map<std::string, std::string> Owners(size_t via,
                                            bool must_answer = true) {
    v1::ListFleetsResponse listed;
    grpc::Status status = Stub(via)->ListFleets(
        MakeContext().get(), v1::ListFleetsRequest(), &listed);
    if (must_answer) EXPECT_TRUE(status.ok()) << Describe(status);
    std::map<std::string, std::string> owners;
    for (const v1::FleetSummary& fleet : listed.fleets()) {
      owners[fleet.fleet_id()] = fleet.replica();
    }
    return owners;
  }

  size_t ReplicaAt(const std::string& address) const {
    for (size_t i = 0; i < ports_.size(); ++i) {
      if (address == absl::StrCat("127.0.0.1:", ports_[i])) return i;
    }
    return ports_.size();
  }

  TempDir dir_{"fleetmem-cluster-"};
  std::vector<std::unique_ptr<ServerProcess>> nats_;
  // Uploads, calls, the owner of fleet-0 killed, and a new replica whose
  // fleets are compared trace by trace with the survivors' (below).
  void OwnerLossScenario(bool snapshots);

  std::string nats_urls_;  // nats://HOST:PORT,...
  // Each fleet's owner stores a snapshot (and trims the log) this often.
  uint64_t snapshot_every_ = 1000;
  std::string extra_config_;  // more of the replicas' config files
  std::vector<std::unique_ptr<ServerProcess>> replicas_;
  std::vector<int> ports_;
  std::vector<int> http_ports_;
};

// With `snapshots`, owners store one every two entries and trim the logs
// as they go, so the new replica restores each fleet's latest snapshot and
// applies the tail; without, it rebuilds every fleet from the log alone.
void ClusterIntegrationTest::OwnerLossScenario(bool snapshots) {
  snapshot_every_ = snapshots ? 2 : 0;
  StartNats();
  for (size_t i = 0; i < 3; ++i) StartReplica(i);

  // Uploads through every replica; a retry of the same traces is
  // recognised by the log.
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    for (int robot = 0; robot < kRobots; ++robot) {
      const size_t via = static_cast<size_t>(fleet + robot) % 3;
      // Every trace acknowledged once. A call that failed part way (its
      // fleet changing owner: the balancing hands fleets over in the first
      // rounds) was retried by UploadVia, and what the failed call stored
      // is answered as duplicates then.
      v1::UploadTracesResponse first = UploadVia(via, fleet, robot, 1, kTraces);
      EXPECT_EQ(first.accepted() + first.duplicates(), kTraces);
      v1::UploadTracesResponse again =
          UploadVia((via + 1) % 3, fleet, robot, 1, kTraces);
      EXPECT_EQ(again.accepted(), 0u);
      EXPECT_EQ(again.duplicates(), kTraces);
    }
  }
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    ASSERT_TRUE(
        WaitForTraces(0, fleet, kRobots * kTraces, std::chrono::seconds(30)));
  }

  // The fleets spread over the three replicas (balancing: the first replica
  // up took them all), then one owner per fleet, the same seen from every
  // replica. Settled: every fleet owned, by the same replicas for a second
  // (a replica acting on announcements a renewal old may still hand a
  // fleet over after the spread first looks done; the fleet has no owner
  // until another takes it, a round later: seen 1 run in 50).
  std::map<size_t, int> per_replica;
  std::map<std::string, std::string> settled;
  Clock::time_point settled_since = Clock::now();
  const auto spread_deadline = Clock::now() + std::chrono::seconds(20);
  do {
    per_replica.clear();
    const std::map<std::string, std::string> now = Owners(1, false);
    for (const auto& [fleet, owner] : now) ++per_replica[ReplicaAt(owner)];
    const bool spread = per_replica.size() == 3 && !per_replica.contains(3);
    if (!spread || now != settled) {
      settled = spread ? now : std::map<std::string, std::string>();
      settled_since = Clock::now();
    } else if (Clock::now() - settled_since >= std::chrono::seconds(1)) {
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  } while (Clock::now() < spread_deadline);
  EXPECT_EQ(per_replica.size(), 3u) << "the fleets are not spread";
  for (const auto& [replica, count] : per_replica) {
    EXPECT_GE(count, 1) << "replica " << replica;
    EXPECT_LE(count, 2) << "replica " << replica;
  }
  const std::map<std::string, std::string> owners = Owners(1);
  ASSERT_EQ(owners.size(), static_cast<size_t>(kFleets));
  for (const auto& [fleet, owner] : owners) {
    EXPECT_LT(ReplicaAt(owner), 3u) << fleet << " owned by \"" << owner << "\"";
  }
  EXPECT_EQ(Owners(2), owners);

  // Each fleet's gauges come from its owner alone, its log applied.
  std::map<std::string, int> shown;
  for (size_t i = 0; i < 3; ++i) {
    const std::string text = Metrics(http_ports_[i]);
    ASSERT_FALSE(text.empty()) << "replica " << i;
    for (const auto& [fleet, lag] :
         FleetGauge(text, "fleetmem_cluster_log_lag_entries")) {
      ++shown[fleet];
      EXPECT_EQ(lag, 0) << fleet << " on replica " << i;
      EXPECT_EQ(ReplicaAt(owners.at(fleet)), i) << fleet;
    }
    for (const auto& [fleet, traces] :
         FleetGauge(text, "fleetmem_fleet_traces")) {
      EXPECT_EQ(ReplicaAt(owners.at(fleet)), i) << fleet;
    }
  }
  EXPECT_EQ(shown.size(), static_cast<size_t>(kFleets));
  for (const auto& [fleet, replicas] : shown) EXPECT_EQ(replicas, 1) << fleet;

  // Queries answer alike through every replica (forwarded to the owner).
  // The balancing may still hand a fleet over here: between the release
  // and the next owner's take, calls answer UNAVAILABLE ("retry"), which a
  // client retries (1 of 50 runs met it); so does this one, for 10 s.
  const v1::MemoryTrace probe = MakeTrace(Spec(2, 1, 1, 1), 7);
  const std::vector<float> probe_code(probe.code().begin(), probe.code().end());
  std::vector<std::string> answers;
  for (size_t via = 0; via < 3; ++via) {
    Reply<v1::QueryPlaceResponse> found =
        QueryCode(*Stub(via), FleetId(2), probe_code, 3);
    for (const auto give_up = Clock::now() + std::chrono::seconds(10);
         found.status.error_code() == grpc::StatusCode::UNAVAILABLE &&
         Clock::now() < give_up;) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      found = QueryCode(*Stub(via), FleetId(2), probe_code, 3);
    }
    ASSERT_TRUE(found.ok()) << Describe(found.status);
    ASSERT_GE(found.response.matches_size(), 1);
    EXPECT_EQ(found.response.matches(0).trace().robot_id(), RobotId(1));
    EXPECT_EQ(found.response.matches(0).trace().seq(), 7u);
    answers.push_back(found.response.DebugString());
  }
  EXPECT_EQ(answers[0], answers[1]);
  EXPECT_EQ(answers[0], answers[2]);

  // An upload the owner would refuse is refused by whichever replica
  // receives it, before anything is appended (here: another dimension).
  TraceSpec other_dimension = Spec(2, 0, 5000, 1);
  other_dimension.dimension = 16;
  const std::vector<v1::MemoryTrace> wrong = MakeTraces(other_dimension);
  for (size_t via = 0; via < 3; ++via) {
    Reply<v1::UploadTracesResponse> refused =
        UploadTraces(*Stub(via), FleetId(2), wrong);
    EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
        << "replica " << via << ": " << Describe(refused.status);
  }

  // SampleReplay through a replica that does not own the fleet: appended
  // to the log by the owner, counted once.
  const std::string owner0 = owners.at(FleetId(0));
  const size_t not_owner = (ReplicaAt(owner0) + 1) % 3;
  Reply<v1::SampleReplayResponse> sample =
      SampleReplay(*Stub(not_owner), FleetId(0), RobotId(0), 20);
  ASSERT_TRUE(sample.ok()) << Describe(sample.status);
  EXPECT_EQ(sample.response.traces_size(), 20);
  Reply<v1::ConsolidateResponse> consolidated =
      Consolidate(*Stub(not_owner), FleetId(1));
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  ASSERT_TRUE(
      WaitForTraces(not_owner, 1, kRobots * kTraces, std::chrono::seconds(5)));
  Reply<v1::GetStatsResponse> after_consolidation =
      GetStats(*Stub(not_owner), FleetId(1));
  EXPECT_EQ(after_consolidation.response.pending_traces(), 0u);

  // DeleteTraces through a replica that does not own the fleet: logged by
  // the owner and applied there; the deleted traces are found through no
  // replica (nor by the new replica that rebuilds the fleets below).
  // Retried on UNAVAILABLE, as a client does (a hand-over, above).
  const auto retried = [](const std::function<grpc::Status()>& call) {
    grpc::Status status = call();
    for (const auto give_up = Clock::now() + std::chrono::seconds(10);
         status.error_code() == grpc::StatusCode::UNAVAILABLE &&
         Clock::now() < give_up;) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      status = call();
    }
    return status;
  };
  const size_t not_owner2 = (ReplicaAt(owners.at(FleetId(2))) + 1) % 3;
  v1::DeleteTracesRequest remove;
  remove.set_fleet_id(FleetId(2));
  remove.set_robot_id(RobotId(0));
  remove.set_seq_first(1);
  remove.set_seq_last(100);
  v1::DeleteTracesResponse removed;
  const grpc::Status deleted = retried([&] {
    auto context = MakeContext();
    return Stub(not_owner2)->DeleteTraces(context.get(), remove, &removed);
  });
  ASSERT_TRUE(deleted.ok()) << Describe(deleted);
  EXPECT_GT(removed.deleted(), 0u);
  v1::GetTracesRequest asked;
  asked.set_fleet_id(FleetId(2));
  for (uint64_t seq = 1; seq <= 110; ++seq) {
    v1::TraceKey* key = asked.add_keys();
    key->set_robot_id(RobotId(0));
    key->set_seq(seq);
  }
  for (size_t via = 0; via < 3; ++via) {
    v1::GetTracesResponse got;
    const grpc::Status read = retried([&] {
      got.Clear();
      auto context = MakeContext();
      return Stub(via)->GetTraces(context.get(), asked, &got);
    });
    ASSERT_TRUE(read.ok()) << Describe(read);
    for (const v1::MemoryTrace& trace : got.traces()) {
      EXPECT_GT(trace.seq(), 100u) << "replica " << via;
    }
    EXPECT_GE(got.missing_size(), 100) << "replica " << via;
  }

  // kill -9 the owner of fleet-0 while uploads go on through the others:
  // they are acknowledged once another replica took fleet-0 (until then
  // they are refused, UNAVAILABLE, and UploadVia retries: the owner admits
  // a fleet's uploads), and fleet-0 is served again once its lease expired
  // and another replica caught up.
  const size_t killed = ReplicaAt(owner0);
  const size_t survivor = (killed + 1) % 3;
  replicas_[killed]->Kill();
  const auto killed_at = Clock::now();
  v1::UploadTracesResponse during = UploadVia(survivor, 0, 0, kTraces + 1, 100);
  EXPECT_EQ(during.accepted(), 100u);
  ASSERT_TRUE(WaitForTraces(survivor, 0, kRobots * kTraces + 100,
                            std::chrono::seconds(20)));
  const double recovered =
      std::chrono::duration<double>(Clock::now() - killed_at).count();
  std::cout << "fleet-0 served again " << recovered
            << " s after its owner was killed (lease 1 s)" << std::endl;
  EXPECT_LT(recovered, 10.0);
  for (int fleet = 1; fleet < kFleets; ++fleet) {
    ASSERT_TRUE(WaitForTraces(survivor, fleet, kRobots * kTraces,
                              std::chrono::seconds(10)));
  }
  const std::map<std::string, std::string> after = Owners(survivor);
  for (const auto& [fleet, owner] : after) {
    EXPECT_NE(ReplicaAt(owner), killed) << fleet;
    EXPECT_LT(ReplicaAt(owner), 3u) << fleet;
  }

  // A fleet made by CreateFleet through one survivor, its settings read
  // and changed through the other (forwarded to its owner), and its bound
  // held by the uploads that follow.
  const size_t other = 3 - killed - survivor;
  v1::CreateFleetRequest create;
  create.set_fleet_id("fleet-made");
  const v1::MemoryTrace shape = MakeTraces(Spec(0, 0, 1, 1))[0];
  create.mutable_settings()->set_code_dimension(
      static_cast<uint32_t>(shape.code_size()));
  create.mutable_settings()->set_encoder_version(shape.encoder_version());
  create.mutable_settings()->set_max_clusters(4);
  v1::CreateFleetResponse made;
  const grpc::Status created = retried([&] {
    auto context = MakeContext();
    return Stub(survivor)->CreateFleet(context.get(), create, &made);
  });
  ASSERT_TRUE(created.ok()) << Describe(created);
  // The second creation through the other survivor: ALREADY_EXISTS once
  // it reads the fleet's log (UNAVAILABLE, retried, while JetStream is
  // still busy with the killed owner's fleets: seen under the sanitizer).
  v1::CreateFleetResponse again;
  const grpc::Status created_again = retried([&] {
    auto context = MakeContext();
    return Stub(other)->CreateFleet(context.get(), create, &again);
  });
  EXPECT_EQ(created_again.error_code(), grpc::StatusCode::ALREADY_EXISTS)
      << Describe(created_again);
  v1::UpdateFleetRequest update;
  update.set_fleet_id("fleet-made");
  update.mutable_settings()->set_max_clusters(3);
  v1::UpdateFleetResponse updated;
  const grpc::Status changed = retried([&] {
    auto context = MakeContext();
    return Stub(other)->UpdateFleet(context.get(), update, &updated);
  });
  ASSERT_TRUE(changed.ok()) << Describe(changed);
  EXPECT_EQ(updated.settings().max_clusters(), 3u);
  for (int robot = 0; robot < kRobots; ++robot) {
    const std::vector<v1::MemoryTrace> traces =
        MakeTraces(Spec(0, robot, 1, kTraces));
    Reply<v1::UploadTracesResponse> uploaded =
        UploadTraces(*Stub(other), "fleet-made", traces);
    ASSERT_TRUE(uploaded.ok()) << Describe(uploaded.status);
  }
  for (const size_t via : {survivor, other}) {
    v1::GetFleetRequest get;
    get.set_fleet_id("fleet-made");
    v1::GetFleetResponse got;
    const grpc::Status read = retried([&] {
      auto context = MakeContext();
      return Stub(via)->GetFleet(context.get(), get, &got);
    });
    ASSERT_TRUE(read.ok()) << Describe(read);
    EXPECT_TRUE(got.fleet().own_settings()) << "replica " << via;
    EXPECT_EQ(got.fleet().settings().max_clusters(), 3u) << "replica " << via;
    EXPECT_LE(got.fleet().clusters(), 3u) << "replica " << via;
  }
  // An alias made through one survivor names the fleet on the other (the
  // shared bucket); then the fleet is deleted through the other.
  v1::CreateAliasRequest alias;
  alias.set_alias("made");
  alias.set_fleet_id("fleet-made");
  v1::CreateAliasResponse aliased;
  grpc::Status status =
      Stub(survivor)->CreateAlias(MakeContext().get(), alias, &aliased);
  ASSERT_TRUE(status.ok()) << Describe(status);
  Reply<v1::GetStatsResponse> through;
  for (int i = 0; i < 100; ++i) {
    through = GetStatsApplied(*Stub(other), "made");
    if (through.ok()) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  ASSERT_TRUE(through.ok()) << Describe(through.status);
  EXPECT_GT(through.response.traces() + through.response.pending_traces(), 0u);
  v1::DeleteFleetRequest drop;
  drop.set_fleet_id("fleet-made");
  v1::DeleteFleetResponse dropped;
  const grpc::Status aliased_delete = retried([&] {
    auto context = MakeContext();
    return Stub(other)->DeleteFleet(context.get(), drop, &dropped);
  });
  EXPECT_EQ(aliased_delete.error_code(),
            grpc::StatusCode::FAILED_PRECONDITION)  // the alias names it
      << Describe(aliased_delete);
  v1::DeleteAliasRequest unalias;
  unalias.set_alias("made");
  v1::DeleteAliasResponse unaliased;
  status = Stub(other)->DeleteAlias(MakeContext().get(), unalias, &unaliased);
  ASSERT_TRUE(status.ok()) << Describe(status);
  status = retried([&] {
    auto context = MakeContext();
    return Stub(other)->DeleteFleet(context.get(), drop, &dropped);
  });
  ASSERT_TRUE(status.ok()) << Describe(status);
  EXPECT_EQ(dropped.traces_deleted(),
            through.response.traces() + through.response.pending_traces());
  EXPECT_EQ(GetStats(*Stub(survivor), "fleet-made").status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  v1::ListFleetsResponse fleets;
  status = Stub(survivor)->ListFleets(MakeContext().get(),
                                      v1::ListFleetsRequest(), &fleets);
  ASSERT_TRUE(status.ok()) << Describe(status);
  for (const v1::FleetSummary& fleet : fleets.fleets()) {
    EXPECT_NE(fleet.fleet_id(), "fleet-made") << fleet.DebugString();
  }
  // Its data left JetStream (its owner snapshotted the deleted fleet and
  // trimmed the log): the id makes a fleet of another shape, through the
  // replica that did not delete it (its cached shape is read again);
  // ALREADY_EXISTS is retried until the owner's snapshot is written.
  // Without snapshots the log keeps the deleted fleet's entries, and with
  // them its shape (docs/distributed.md).
  if (snapshots) {
    v1::CreateFleetRequest remake;
    remake.set_fleet_id("fleet-made");
    remake.mutable_settings()->set_code_dimension(8);
    remake.mutable_settings()->set_encoder_version("enc-remade");
    v1::CreateFleetResponse remade;
    status = Stub(survivor)->CreateFleet(MakeContext().get(), remake, &remade);
    for (const auto give_up = Clock::now() + std::chrono::seconds(10);
         (status.error_code() == grpc::StatusCode::ALREADY_EXISTS ||
          status.error_code() == grpc::StatusCode::UNAVAILABLE) &&
         Clock::now() < give_up;) {
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
      status =
          Stub(survivor)->CreateFleet(MakeContext().get(), remake, &remade);
    }
    ASSERT_TRUE(status.ok()) << Describe(status);
    TraceSpec small = Spec(0, 0, 1, 20);
    small.dimension = 8;
    std::vector<v1::MemoryTrace> small_traces = MakeTraces(small);
    for (v1::MemoryTrace& trace : small_traces) {
      trace.set_encoder_version("enc-remade");
    }
    for (const size_t via : {other, survivor}) {
      Reply<v1::UploadTracesResponse> uploaded =
          UploadTraces(*Stub(via), "fleet-made", small_traces);
      for (const auto give_up = Clock::now() + std::chrono::seconds(10);
           uploaded.status.error_code() == grpc::StatusCode::UNAVAILABLE &&
           Clock::now() < give_up;) {
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
        uploaded = UploadTraces(*Stub(via), "fleet-made", small_traces);
      }
      ASSERT_TRUE(uploaded.ok())
          << "replica " << via << ": " << Describe(uploaded.status);
    }
    // Applied by the owner a moment after the acknowledgement (NOT_FOUND
    // until its CreateFleet entry is).
    Reply<v1::GetStatsResponse> remade_stats;
    for (const auto give_up = Clock::now() + std::chrono::seconds(10);;) {
      remade_stats = GetStatsApplied(*Stub(other), "fleet-made");
      if (remade_stats.ok() || Clock::now() >= give_up) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    ASSERT_TRUE(remade_stats.ok()) << Describe(remade_stats.status);
    EXPECT_EQ(remade_stats.response.backlog_traces(), 0u);
    EXPECT_EQ(remade_stats.response.code_dimension(), 8u);
    EXPECT_EQ(
        remade_stats.response.traces() + remade_stats.response.pending_traces(),
        20u);
  }

  // What the survivors hold, trace by trace, against a new replica that
  // rebuilds every fleet from its latest snapshot and the log after it (the
  // survivors stop cleanly and hand their fleets over; the logs were
  // trimmed, so the snapshots are needed).
  std::map<int, std::vector<std::string>> before;
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    grpc::Status listed;
    before[fleet] = Listing(*Stub(survivor), FleetId(fleet), &listed);
    ASSERT_TRUE(listed.ok()) << Describe(listed);
  }
  std::set<std::string> distinct(before[0].begin(), before[0].end());
  EXPECT_EQ(distinct.size(), before[0].size());
  for (size_t i = 0; i < 3; ++i) {
    if (i == killed) continue;
    absl::StatusOr<int> stopped = replicas_[i]->Stop();
    ASSERT_TRUE(stopped.ok()) << stopped.status();
    EXPECT_EQ(*stopped, 0);
  }
  StartReplica(3);
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    ASSERT_TRUE(WaitForTraces(3, fleet,
                              kRobots * kTraces + (fleet == 0 ? 100 : 0),
                              std::chrono::seconds(20)));
    // The count is reached at the last upload; a Consolidate or a sample
    // after it may still be applying.
    const auto deadline = Clock::now() + std::chrono::seconds(10);
    grpc::Status listed;
    std::vector<std::string> rebuilt;
    do {
      rebuilt = Listing(*Stub(3), FleetId(fleet), &listed);
      if (rebuilt == before[fleet]) break;
      std::this_thread::sleep_for(std::chrono::milliseconds(100));
    } while (Clock::now() < deadline);
    EXPECT_EQ(rebuilt, before[fleet]) << FleetId(fleet);
    EXPECT_TRUE(listed.ok()) << Describe(listed);
  }
  // Each fleet came from a snapshot there (with snapshots), or from its
  // whole log (without).
  const std::string log = ReadFileOrEmpty(dir_.Join("replica-3.log"));
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    EXPECT_EQ(
        absl::StrContains(log, absl::StrCat("fleet \"", FleetId(fleet),
                                            "\" restored from its snapshot")),
        snapshots)
        << FleetId(fleet);
  }
}

TEST_F(ClusterIntegrationTest, FleetsServedByOneOwnerSurviveItsLoss) {
  OwnerLossScenario(/*snapshots=*/true);
}

TEST_F(ClusterIntegrationTest, AFleetRebuiltFromTheLogAloneIsTheSame) {
  OwnerLossScenario(/*snapshots=*/false);
}

// Upload rates are the receiving replica's: a robot over its rate is
// refused there (RESOURCE_EXHAUSTED naming the limit) and nothing of the
// refused upload reaches the log; the owner applies what was accepted.
TEST_F(ClusterIntegrationTest, TheReceivingReplicaAppliesUploadRates) {
  extra_config_ = "limits { robot_traces_per_second: 50 burst_seconds: 2 }";
  StartNats();
  StartReplica(0);
  // The burst: 2 s of 50 traces/s.
  const std::vector<v1::MemoryTrace> first = MakeTraces(Spec(0, 0, 1, 100));
  Reply<v1::UploadTracesResponse> accepted =
      UploadTraces(*Stub(0), FleetId(0), first, 100);
  ASSERT_TRUE(accepted.ok()) << Describe(accepted.status);
  EXPECT_EQ(accepted.response.accepted(), 100u);
  const std::vector<v1::MemoryTrace> more = MakeTraces(Spec(0, 0, 101, 100));
  Reply<v1::UploadTracesResponse> refused =
      UploadTraces(*Stub(0), FleetId(0), more, 100);
  EXPECT_EQ(refused.status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED)
      << Describe(refused.status);
  EXPECT_NE(refused.status.error_message().find("robot_traces_per_second"),
            std::string::npos)
      << Describe(refused.status);
  ASSERT_TRUE(WaitForTraces(0, 0, 100, std::chrono::seconds(20)));
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  Reply<v1::GetStatsResponse> stats = GetStats(*Stub(0), FleetId(0));
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(Received(stats.response), 100u);
}

// The limits on what a fleet holds refuse an upload before it is
// acknowledged, in distributed mode as in embedded mode (engine/
// admission.h): the same uploads get the same answers, naming the same
// limit, whichever replica receives them (the fleet's owner admits its
// load: the other replicas forward to it), and nothing refused reaches a
// log. Before, distributed mode checked them only when the owner applied
// an entry, and an entry past max_traces_per_fleet stopped its fleet's log.
TEST_F(ClusterIntegrationTest, LimitsRefuseTheSameUploadsAsEmbeddedMode) {
  const std::string limits =
      "limits { max_traces_per_fleet: 50 max_fleets: 2 }";
  using StubFor =
      std::function<std::unique_ptr<v1::MemoryService::Stub>(size_t)>;
  // What each upload of the scenario was answered ("OK 40", or the code and
  // the limit named), against the servers `stub(0)` and `stub(1)`.
  const auto scenario = [](const StubFor& stub) {
    std::vector<std::string> answers;
    const auto upload = [&](size_t via, int fleet, uint64_t first,
                            size_t count) {
      const std::vector<v1::MemoryTrace> traces =
          MakeTraces(Spec(fleet, 0, first, count));
      // UNAVAILABLE (a fleet between owners) is retried, as robots do.
      Reply<v1::UploadTracesResponse> reply;
      const auto give_up = Clock::now() + std::chrono::seconds(20);
      do {
        reply = UploadTraces(*stub(via), FleetId(fleet), traces, count);
        if (reply.status.error_code() != grpc::StatusCode::UNAVAILABLE) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      } while (Clock::now() < give_up);
      std::string answer = reply.ok()
                               ? absl::StrCat("OK ", reply.response.accepted())
                               : absl::StrCat(reply.status.error_code());
      for (const char* limit : {"max_traces_per_fleet", "max_fleets"}) {
        if (reply.status.error_message().find(limit) != std::string::npos) {
          absl::StrAppend(&answer, " ", limit);
        }
      }
      answers.push_back(answer);
    };
    // Waits until `fleet` holds `traces`, applied (GetStats through via).
    const auto applied = [&](size_t via, int fleet, uint64_t traces) {
      const auto give_up = Clock::now() + std::chrono::seconds(20);
      Reply<v1::GetStatsResponse> stats;
      do {
        stats = GetStats(*stub(via), FleetId(fleet));
        if (stats.ok() && Received(stats.response) == traces) return;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
      } while (Clock::now() < give_up);
      ADD_FAILURE() << FleetId(fleet) << ": "
                    << (stats.ok() ? absl::StrCat(Received(stats.response))
                                   : Describe(stats.status));
    };
    upload(0, 0, 1, 40);
    applied(1, 0, 40);
    upload(1, 0, 41, 20);  // 60 > 50
    upload(0, 0, 41, 20);
    upload(1, 0, 41, 10);  // 50: at the limit
    upload(1, 1, 1, 5);    // a second fleet
    applied(0, 1, 5);
    upload(0, 2, 1, 5);  // a third: max_fleets
    upload(1, 2, 1, 5);
    applied(0, 0, 50);
    return answers;
  };
  const std::vector<std::string> expected = {
      "OK 40",
      "8 max_traces_per_fleet",  // RESOURCE_EXHAUSTED
      "8 max_traces_per_fleet",
      "OK 10",
      "OK 5",
      "8 max_fleets",
      "8 max_fleets"};

  extra_config_ = limits;
  StartNats();
  StartReplica(0);
  StartReplica(1);
  const std::vector<std::string> distributed =
      scenario([this](size_t i) { return Stub(i); });
  EXPECT_EQ(distributed, expected);

  const std::string data = dir_.Join("embedded");
  std::filesystem::create_directories(data);
  const std::string config = dir_.Join("embedded.cfg");
  std::ofstream(config) << limits << "\n";
  ServerOptions options;
  options.data_dir = data;
  options.config_file = config;
  const int port = FreePort();
  options.listen = absl::StrCat("127.0.0.1:", port);
  options.log_file = dir_.Join("embedded.log");
  ServerProcess embedded_server(options);
  ASSERT_TRUE(embedded_server.Start().ok());
  const std::vector<std::string> embedded = scenario(
      [port](size_t) { return MakeStub(absl::StrCat("127.0.0.1:", port)); });
  EXPECT_EQ(embedded, expected);
}

// Two robots create one fleet at once through two replicas with different
// code dimensions: exactly one is acknowledged, the other refused
// (INVALID_ARGUMENT), never both (the creating upload is appended only as
// the log's first entry).
TEST_F(ClusterIntegrationTest, OneOfTwoUploadsCreatingAFleetAtOnceWins) {
  StartNats();
  StartReplica(0);
  StartReplica(1);
  int both = 0, one = 0;
  for (int attempt = 0; attempt < 12; ++attempt) {
    const std::string fleet = absl::StrCat("race-", attempt);
    TraceSpec narrow = Spec(0, 0, 1, 50);
    TraceSpec wide = Spec(0, 1, 1, 50);
    wide.dimension = 16;
    const std::vector<v1::MemoryTrace> a = MakeTraces(narrow);
    const std::vector<v1::MemoryTrace> b = MakeTraces(wide);
    // As a robot does, an upload is retried while UNAVAILABLE (a stream
    // JetStream is still making answers "no responders").
    const auto upload = [&](size_t via,
                            const std::vector<v1::MemoryTrace>& traces) {
      Reply<v1::UploadTracesResponse> reply;
      const auto deadline = Clock::now() + std::chrono::seconds(20);
      do {
        reply = UploadTraces(*Stub(via), fleet, traces, 50);
        if (reply.status.error_code() != grpc::StatusCode::UNAVAILABLE) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      } while (Clock::now() < deadline);
      return reply;
    };
    Reply<v1::UploadTracesResponse> reply_a, reply_b;
    std::thread other([&] { reply_b = upload(1, b); });
    reply_a = upload(0, a);
    other.join();
    if (reply_a.ok() && reply_b.ok()) ++both;
    if (reply_a.ok() != reply_b.ok()) ++one;
    for (const Reply<v1::UploadTracesResponse>* reply : {&reply_a, &reply_b}) {
      if (!reply->ok()) {
        EXPECT_EQ(reply->status.error_code(),
                  grpc::StatusCode::INVALID_ARGUMENT)
            << Describe(reply->status);
      }
    }
  }
  EXPECT_EQ(both, 0) << "both uploads creating a fleet were acknowledged";
  EXPECT_EQ(one, 12);
}

// Seconds until GetStats of every fleet answers through replica `via`
// (calls of 1 s), or -1 after `timeout`.
double UntilServed(const std::string& address, int fleets,
                   std::chrono::seconds timeout) {
  const auto start = Clock::now();
  std::unique_ptr<v1::MemoryService::Stub> stub = MakeStub(address);
  for (int fleet = 0; fleet < fleets; ++fleet) {
    while (true) {
      v1::GetStatsRequest request;
      request.set_fleet_id(FleetId(fleet));
      v1::GetStatsResponse response;
      if (stub->GetStats(MakeContext(std::chrono::seconds(1)).get(), request,
                         &response)
              .ok()) {
        break;
      }
      if (Clock::now() - start > timeout) return -1;
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
  }
  return std::chrono::duration<double>(Clock::now() - start).count();
}

// The faults of a cluster under load: three NATS servers (three copies of
// each log) and three replicas; a robot per fleet uploads through the
// replicas in turn, retrying a failed batch through the next. One NATS
// server is killed, then the owner of fleet-0 is paused (SIGSTOP: it can
// neither renew its leases nor answer) for 4 s and resumed. Every
// acknowledged trace is held exactly once afterwards, and every fleet is
// served again within 10 s of each fault. Owners store snapshots and trim
// the logs throughout (every 10 entries).
TEST_F(ClusterIntegrationTest, SurvivesALostNatsServerAndAPausedReplica) {
  snapshot_every_ = 10;
  StartNatsCluster();
  for (size_t i = 0; i < 3; ++i) StartReplica(i);
  std::atomic<bool> stop{false};
  std::vector<std::atomic<uint64_t>> acknowledged(kFleets);
  std::vector<std::thread> robots;
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    robots.emplace_back([&, fleet] {
      uint64_t seq = 1;
      size_t via = static_cast<size_t>(fleet);
      while (!stop.load()) {
        const std::vector<v1::MemoryTrace> batch =
            MakeTraces(Spec(fleet, 0, seq, 20));
        Reply<v1::UploadTracesResponse> reply = UploadTraces(
            *Stub(via % 3), FleetId(fleet), batch, 20, std::chrono::seconds(2));
        ++via;
        if (reply.ok()) {
          seq += 20;
          acknowledged[fleet].store(seq - 1);
        }
        // About 200 traces/s per fleet, or a retry 100 ms after a failure.
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
      }
    });
  }
  const auto stop_robots = [&] {
    stop.store(true);
    for (std::thread& robot : robots) {
      if (robot.joinable()) robot.join();
    }
  };
  // Joined also when an assertion returns early.
  absl::Cleanup join_robots = stop_robots;
  std::this_thread::sleep_for(std::chrono::seconds(2));

  nats_[1]->Kill();
  const double after_nats = UntilServed(absl::StrCat("127.0.0.1:", ports_[0]),
                                        kFleets, std::chrono::seconds(30));
  std::this_thread::sleep_for(std::chrono::seconds(2));

  // The owner of fleet-0 once the cluster settled: the same in two looks
  // a second apart (with 1 s leases, some may have expired while JetStream
  // elected the lease bucket's new leader, and moved).
  const auto owner_of_fleet0 = [&] {
    // While JetStream elects its leaders ListFleets may fail: asked again.
    const std::map<std::string, std::string> owners = Owners(0, false);
    auto found = owners.find(FleetId(0));
    return found == owners.end() ? size_t{3} : ReplicaAt(found->second);
  };
  size_t paused = 3;
  for (const auto settle = Clock::now() + std::chrono::seconds(30);
       Clock::now() < settle;) {
    const size_t seen = owner_of_fleet0();
    std::this_thread::sleep_for(std::chrono::seconds(1));
    if (seen < 3 && owner_of_fleet0() == seen) {
      paused = seen;
      break;
    }
  }
  ASSERT_LT(paused, 3u) << "fleet-0 has no settled owner";
  const size_t other = (paused + 1) % 3;
  // A watch of fleet-0 on its owner: it must end, not stall, once the owner
  // has lost the fleet.
  grpc::Status watch_end;
  std::atomic<bool> watch_ended{false};
  std::unique_ptr<v1::MemoryService::Stub> watch_stub = Stub(paused);
  grpc::ClientContext watch_context;
  watch_context.set_deadline(std::chrono::system_clock::now() +
                             std::chrono::seconds(90));
  std::thread watcher([&] {
    v1::WatchMemoryRequest request;
    request.set_fleet_id(FleetId(0));
    std::unique_ptr<grpc::ClientReader<v1::MemoryEvent>> reader =
        watch_stub->WatchMemory(&watch_context, request);
    v1::MemoryEvent event;
    while (reader->Read(&event)) {
    }
    watch_end = reader->Finish();
    watch_ended.store(true);
  });
  absl::Cleanup join_watcher = [&] {
    watch_context.TryCancel();
    watcher.join();
  };
  std::this_thread::sleep_for(std::chrono::milliseconds(500));
  replicas_[paused]->Signal(SIGSTOP);
  const double after_pause =
      UntilServed(absl::StrCat("127.0.0.1:", ports_[other]), kFleets,
                  std::chrono::seconds(20));
  std::this_thread::sleep_for(std::chrono::seconds(4) -
                              std::chrono::milliseconds(static_cast<int>(
                                  std::max(0.0, after_pause) * 1000)));
  replicas_[paused]->Signal(SIGCONT);
  const auto resumed = Clock::now();
  while (!watch_ended.load() &&
         Clock::now() - resumed < std::chrono::seconds(15)) {
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  std::cout << "fault                 served again after\n"
            << "NATS server killed    " << after_nats << " s\n"
            << "owner paused 4 s      " << after_pause << " s\n";
  // Who took and lost which fleet, when (docs/distributed.md, "The paused
  // owner").
  for (size_t i = 0; i < replicas_.size(); ++i) {
    for (absl::string_view line : absl::StrSplit(
             ReadFileOrEmpty(dir_.Join(absl::StrCat("replica-", i, ".log"))),
             '\n')) {
      if (absl::StrContains(line, "\" taken (") ||
          absl::StrContains(line, "\" lost: ")) {
        std::cout << "replica " << i << (i == paused ? " (paused) " : " ")
                  << line << "\n";
      }
    }
  }
  ASSERT_TRUE(watch_ended.load()) << "the watch on the old owner goes on";
  EXPECT_EQ(watch_end.error_code(), grpc::StatusCode::UNAVAILABLE)
      << Describe(watch_end);
  // Moved, or (when the pause caught the replica still catching up on a
  // take of the fleet, whose lease it then lost) "taken ... a moment ago
  // ... retry": either tells the robot to watch again, and the retry finds
  // the new owner. Seen twice in ctest runs of 2026-11-30/12-01.
  EXPECT_TRUE(absl::StrContains(watch_end.error_message(),
                                "moved to another replica") ||
              absl::StrContains(watch_end.error_message(),
                                "a moment ago and is applied through entry"))
      << Describe(watch_end);
  std::this_thread::sleep_for(std::chrono::seconds(1));
  stop_robots();

  // A lost NATS server costs JetStream's election of new leaders for the
  // streams and the lease bucket it led (seconds in nats-server 2.9); the
  // issue's 10 s is for the loss of a fleet's owner. Measured 0.003-15.6 s
  // (2026-11-28: 100 runs of this case, 3 over 15 s), then 0.01-19.5 s
  // (2026-11-29: 60 runs, beside builds and other tests; docs/
  // distributed.md): the bound is 30 s, above the elections' spread, below
  // a cluster that does not recover.
  EXPECT_GE(after_nats, 0.0);
  EXPECT_LT(after_nats, 30.0);
  EXPECT_GE(after_pause, 0.0);
  EXPECT_LT(after_pause, 10.0);

  // Every acknowledged trace, once, through every replica (the resumed one
  // forwards to the new owners); the batch each robot had in flight when it
  // stopped may be stored too, its answer lost to the robot's deadline.
  for (int fleet = 0; fleet < kFleets; ++fleet) {
    const uint64_t want = acknowledged[fleet].load();
    EXPECT_GT(want, 0u) << FleetId(fleet);
    for (size_t via = 0; via < 3; ++via) {
      ASSERT_TRUE(WaitForTraces(via, fleet, want, std::chrono::seconds(20),
                                /*unacknowledged=*/20))
          << "replica " << via;
    }
    grpc::Status listed;
    const std::vector<std::string> traces =
        Listing(*Stub(paused), FleetId(fleet), &listed);
    ASSERT_TRUE(listed.ok()) << Describe(listed);
    std::set<std::string> distinct(traces.begin(), traces.end());
    EXPECT_EQ(distinct.size(), traces.size()) << FleetId(fleet);
  }
  const std::map<std::string, std::string> owners = Owners(other);
  EXPECT_EQ(Owners(paused), owners);
}

}  // namespace
}  // namespace fleetmem::testing
