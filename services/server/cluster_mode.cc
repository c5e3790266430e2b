#include "services/server/cluster_mode.h"

#include <algorithm>
#include <chrono>
#include <fstream>
#include <sstream>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "services/cluster/materialiser.h"
#include "services/common/files.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"

namespace fleetmem::server {
namespace {

absl::StatusOr<std::string> ReadWhole(const std::string& what,
                                      const std::string& path) {
  absl::StatusOr<std::string> text = files::ReadFile(path);
  if (!text.ok()) {
    return absl::Status(text.status().code(),
                        absl::StrCat(what, " ", path, ": cannot be read"));
  }
  return text;
}

}  // namespace

absl::StatusOr<std::unique_ptr<cluster::ReplicatedMemory>> StartClusterMode(
    const ServerConfig& config, engine::MemoryEngine* engine) {
  const ClusterConfig& cluster = config.cluster;
  transport::PeerOptions peers;
  if (!cluster.peer_token_file.empty()) {
    absl::StatusOr<std::string> token =
        ReadWhole("cluster.peer_token_file", cluster.peer_token_file);
    if (!token.ok()) return token.status();
    peers.token = std::string(absl::StripAsciiWhitespace(*token));
    if (peers.token.find(':') == std::string::npos) {
      return absl::InvalidArgumentError(
          absl::StrCat("cluster.peer_token_file ", cluster.peer_token_file,
                       ": not a NAME:SECRET token"));
    }
  }
  const bool tls = !config.security.tls_cert_file.empty();
  const std::string& ca_file = cluster.peer_ca_file.empty()
                                   ? config.security.tls_client_ca_file
                                   : cluster.peer_ca_file;
  if (tls) {
    if (ca_file.empty()) {
      return absl::InvalidArgumentError(
          "cluster.peer_ca_file: required with TLS on (the CA the other "
          "replicas' certificates are checked against)");
    }
    absl::StatusOr<std::string> ca = ReadWhole("cluster.peer_ca_file", ca_file);
    if (!ca.ok()) return ca.status();
    peers.ca_pem = *std::move(ca);
    peers.tls_server_name = cluster.peer_tls_server_name;
  }
  // NATS may still be starting (a JetStream cluster elects its leader
  // some seconds after its servers listen): retried for a while.
  const absl::Time give_up = absl::Now() + cluster.connect_timeout;
  absl::Duration backoff = absl::Milliseconds(200);
  absl::StatusOr<std::unique_ptr<cluster::NatsFleetLog>> log =
      cluster::NatsFleetLog::Connect(cluster.nats);
  while (!log.ok() &&
         (absl::IsUnavailable(log.status()) ||
          absl::IsDeadlineExceeded(log.status())) &&
         absl::Now() + backoff < give_up) {
    FLEETMEM_LOG(kWarning) << "cluster: " << log.status() << "; retrying in "
                           << backoff;
    absl::SleepFor(backoff);
    backoff = std::min(backoff * 2, absl::Seconds(5));
    log = cluster::NatsFleetLog::Connect(cluster.nats);
  }
  if (!log.ok()) return log.status();
  cluster::ClusterNodeOptions node;
  node.interval = cluster.round_interval;
  node.balance = cluster.balance_fleets;
  node.materialiser.replica_id = cluster.advertise;
  node.materialiser.renew_interval = cluster.nats.lease_ttl / 3;
  node.materialiser.lease_ttl = cluster.nats.lease_ttl;
  node.materialiser.snapshot_every = cluster.snapshot_every_entries;
  node.materialiser.trim_log = cluster.trim_log;
  engine::QuotaOptions rates;  // the rates only; the engine has the rest
  rates.fleet_traces_per_second = config.engine.limits.fleet_traces_per_second;
  rates.fleet_bytes_per_second = config.engine.limits.fleet_bytes_per_second;
  rates.robot_traces_per_second = config.engine.limits.robot_traces_per_second;
  rates.robot_bytes_per_second = config.engine.limits.robot_bytes_per_second;
  rates.burst_seconds = config.engine.limits.burst_seconds;
  return std::make_unique<cluster::ReplicatedMemory>(
      cluster.advertise, cluster.max_entry_bytes,
      config.write_path.max_backlog_traces, rates, *std::move(log),
      std::move(peers), engine, node);
}

}  // namespace fleetmem::server
