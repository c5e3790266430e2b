// Test fixture: a real nats-server with JetStream (Debian's) on a random
// loopback port in a temporary store directory, and NatsFleetLog clients of
// it. For the cluster module's tests only.
#ifndef FLEETMEM_SERVICES_CLUSTER_TESTING_NATS_FIXTURE_H_
#define FLEETMEM_SERVICES_CLUSTER_TESTING_NATS_FIXTURE_H_

#include <iostream>
#include <memory>
#include <utility>

#include "absl/strings/str_cat.h"
#include "gtest/gtest.h"
#include "services/cluster/nats_fleet_log.h"
#include "tests/server_process.h"

namespace fleetmem::cluster {

class NatsFixture : public ::testing::Test {
 protected:
  void SetUp() override {
    ASSERT_FALSE(dir_.path().empty());
    StartNats(testing::NatsServerOptions(dir_.Join("jetstream"),
                                         dir_.Join("nats.log")));
  }
  void TearDown() override {
    if (HasFailure()) {
      std::cerr << "---- nats-server log ----\n"
                << testing::ReadFileOrEmpty(dir_.Join("nats.log")) << "\n";
    }
  }

  void StartNats(testing::ServerOptions options) {
    nats_ = std::make_unique<testing::ServerProcess>(std::move(options));
    absl::Status started = nats_->Start();
    ASSERT_TRUE(started.ok()) << started;
  }

  // One server: one replica; leases expire after 1 s.
  NatsOptions Options() const {
    NatsOptions options;
    options.servers = {absl::StrCat("nats://", nats_->address())};
    options.replicas = 1;
    options.lease_ttl = absl::Seconds(1);
    options.timeout = absl::Seconds(2);
    return options;
  }

  std::unique_ptr<NatsFleetLog> Connect() {
    absl::StatusOr<std::unique_ptr<NatsFleetLog>> log =
        NatsFleetLog::Connect(Options());
    EXPECT_TRUE(log.ok()) << log.status();
    return log.ok() ? *std::move(log) : nullptr;
  }

  testing::TempDir dir_{"fleetmem-nats-"};
  std::unique_ptr<testing::ServerProcess> nats_;
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_TESTING_NATS_FIXTURE_H_
