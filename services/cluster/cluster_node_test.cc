// Two replicas' ownership loops against a real nats-server: every fleet is
// owned by exactly one replica and materialised there; when one replica
// stops (as if killed: its leases are not given up), the other takes its
// fleets once their leases expire, and reaches the same memory.
#include "services/cluster/cluster_node.h"

#include <algorithm>
#include <chrono>
#include <iostream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gtest/gtest.h"
#include "services/cluster/testing/cluster_test_util.h"
#include "services/cluster/testing/nats_fixture.h"

namespace fleetmem::cluster {
namespace {

using testing_util::AppendUploads;
using testing_util::ExpectSameState;
using testing_util::Replica;
using testing_util::StateOf;
using testing_util::Uploads;
using Clock = std::chrono::steady_clock;

using ClusterNodeTest = NatsFixture;

ClusterNodeOptions NodeOptions(const std::string& replica_id) {
  ClusterNodeOptions options;
  options.materialiser.replica_id = replica_id;
  // A third of the fixture's 1 s lease.
  options.materialiser.renew_interval = absl::Milliseconds(300);
  options.interval = absl::Milliseconds(50);
  return options;
}

// True once every fleet is materialised on `replica` as on `embedded`.
bool Materialised(const Replica& replica, const Replica& embedded,
                  const std::vector<std::string>& fleets) {
  for (const std::string& fleet : fleets) {
    absl::StatusOr<engine::FleetStats> got = replica.engine->GetStats(fleet);
    absl::StatusOr<engine::FleetStats> want = embedded.engine->GetStats(fleet);
    if (!got.ok() || !want.ok() || got->robots.size() != want->robots.size()) {
      return false;
    }
    for (size_t i = 0; i < got->robots.size(); ++i) {
      if (got->robots[i].received != want->robots[i].received) return false;
    }
  }
  return true;
}

TEST_F(ClusterNodeTest, OneOwnerPerFleetAndTakeoverAfterAReplicaStops) {
  std::unique_ptr<NatsFleetLog> log_a = Connect();
  std::unique_ptr<NatsFleetLog> log_b = Connect();
  ASSERT_NE(log_a, nullptr);
  ASSERT_NE(log_b, nullptr);
  const std::vector<std::string> fleets = {"north", "south", "east", "west"};
  Replica embedded;
  for (const std::string& fleet : fleets) {
    for (const auto& batch : Uploads()) {
      ASSERT_TRUE(embedded.engine->Upload(fleet, batch).ok());
    }
    AppendUploads(*log_a, fleet, Uploads());
  }

  Replica a, b;
  auto node_a =
      std::make_unique<ClusterNode>(NodeOptions("replica-a"), log_a.get(),
                                    log_a.get(), log_a.get(), a.engine.get());
  ClusterNode node_b(NodeOptions("replica-b"), log_b.get(), log_b.get(),
                     log_b.get(), b.engine.get());
  node_a->Start();
  node_b.Start();
  // Each fleet ends up owned by exactly one of them and materialised there.
  const Clock::time_point start = Clock::now();
  std::vector<std::string> owned_a, owned_b;
  while (Clock::now() - start < std::chrono::seconds(20)) {
    owned_a = node_a->owned();
    owned_b = node_b.owned();
    if (owned_a.size() + owned_b.size() == fleets.size() &&
        Materialised(a, embedded, owned_a) &&
        Materialised(b, embedded, owned_b)) {
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  std::vector<std::string> all = owned_a;
  all.insert(all.end(), owned_b.begin(), owned_b.end());
  std::sort(all.begin(), all.end());
  std::vector<std::string> sorted = fleets;
  std::sort(sorted.begin(), sorted.end());
  ASSERT_EQ(all, sorted) << "a owns " << owned_a.size() << ", b "
                         << owned_b.size();
  for (const std::string& fleet : owned_a) {
    ExpectSameState(StateOf(*a.engine, fleet),
                    StateOf(*embedded.engine, fleet));
  }

  // A stops as if killed: its leases stay until they expire (1 s); then B
  // owns every fleet and has materialised A's from the log.
  const Clock::time_point killed = Clock::now();
  node_a->Stop();
  while (Clock::now() - killed < std::chrono::seconds(20)) {
    if (node_b.owned().size() == fleets.size() &&
        Materialised(b, embedded, fleets)) {
      break;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  const double takeover_s =
      std::chrono::duration<double>(Clock::now() - killed).count();
  ASSERT_EQ(node_b.owned().size(), fleets.size());
  EXPECT_LT(takeover_s, 10.0);  // the bound: served again in 10 s
  std::cout << "takeover of " << owned_a.size() << " fleet(s) after "
            << takeover_s << " s (lease 1 s)\n";
  for (const std::string& fleet : fleets) {
    ExpectSameState(StateOf(*b.engine, fleet),
                    StateOf(*embedded.engine, fleet));
  }

  // A clean stop gives the leases up at once.
  node_b.Stop();
  node_b.ReleaseAll();
  for (const std::string& fleet : fleets) {
    EXPECT_FALSE(log_a->Holder(fleet)->has_value()) << fleet;
  }
}

// Balancing: a replica alone takes every fleet; two that join get their
// share (the first hands fleets over, one per round), and every fleet is
// materialised where it ends up as in the embedded mode.
TEST_F(ClusterNodeTest, ReplicasThatJoinGetTheirShareOfTheFleets) {
  std::vector<std::unique_ptr<NatsFleetLog>> logs;
  for (int i = 0; i < 3; ++i) {
    logs.push_back(Connect());
    ASSERT_NE(logs.back(), nullptr);
  }
  const std::vector<std::string> fleets = {"f1", "f2", "f3", "f4", "f5", "f6"};
  Replica embedded;
  for (const std::string& fleet : fleets) {
    for (const auto& batch : Uploads()) {
      ASSERT_TRUE(embedded.engine->Upload(fleet, batch).ok());
    }
    AppendUploads(*logs[0], fleet, Uploads());
  }
  Replica replicas[3];
  std::vector<std::unique_ptr<ClusterNode>> nodes;
  for (int i = 0; i < 3; ++i) {
    nodes.push_back(std::make_unique<ClusterNode>(
        NodeOptions(absl::StrCat("replica-", i)), logs[i].get(), logs[i].get(),
        logs[i].get(), replicas[i].engine.get()));
  }
  nodes[0]->Start();
  auto wait_for = [&](auto done) {
    const Clock::time_point start = Clock::now();
    while (!done() && Clock::now() - start < std::chrono::seconds(20)) {
      std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return std::chrono::duration<double>(Clock::now() - start).count();
  };
  wait_for([&] { return nodes[0]->owned().size() == fleets.size(); });
  ASSERT_EQ(nodes[0]->owned().size(), fleets.size());

  nodes[1]->Start();
  nodes[2]->Start();
  const double spread_s = wait_for([&] {
    size_t total = 0;
    for (int i = 0; i < 3; ++i) {
      const std::vector<std::string> owned = nodes[i]->owned();
      if (owned.size() != 2 || !Materialised(replicas[i], embedded, owned)) {
        return false;
      }
      total += owned.size();
    }
    return total == fleets.size();
  });
  std::vector<std::string> all;
  for (int i = 0; i < 3; ++i) {
    const std::vector<std::string> owned = nodes[i]->owned();
    EXPECT_EQ(owned.size(), 2u) << "replica-" << i;
    all.insert(all.end(), owned.begin(), owned.end());
    for (const std::string& fleet : owned) {
      ExpectSameState(StateOf(*replicas[i].engine, fleet),
                      StateOf(*embedded.engine, fleet));
    }
  }
  std::sort(all.begin(), all.end());
  EXPECT_EQ(all, fleets);
  std::cout << "6 fleets spread over 3 replicas " << spread_s
            << " s after two joined\n";
  for (auto& node : nodes) node->Stop();
}

}  // namespace
}  // namespace fleetmem::cluster
