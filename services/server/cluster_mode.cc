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

absl::StatusOr<std::unique_ptr<ClusterMode>> ClusterMode::Start(
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
  node.materialiser.snapshot_every = cluster.snapshot_every_entries;
  node.materialiser.trim_log = cluster.trim_log;
  engine::QuotaOptions rates;  // the rates only; the engine has the rest
  rates.fleet_traces_per_second = config.engine.limits.fleet_traces_per_second;
  rates.fleet_bytes_per_second = config.engine.limits.fleet_bytes_per_second;
  rates.robot_traces_per_second = config.engine.limits.robot_traces_per_second;
  rates.robot_bytes_per_second = config.engine.limits.robot_bytes_per_second;
  rates.burst_seconds = config.engine.limits.burst_seconds;
  return std::unique_ptr<ClusterMode>(
      new ClusterMode(cluster.advertise, cluster.max_entry_bytes, rates,
                      *std::move(log), std::move(peers), engine, node));
}

ClusterMode::ClusterMode(std::string self, size_t max_entry_bytes,
                         engine::QuotaOptions rates,
                         std::unique_ptr<cluster::NatsFleetLog> log,
                         transport::PeerOptions peers,
                         engine::MemoryEngine* engine,
                         cluster::ClusterNodeOptions node)
    : self_(std::move(self)),
      max_entry_bytes_(max_entry_bytes),
      rates_(std::move(rates),
             [] {
               return std::chrono::duration<double>(
                          std::chrono::steady_clock::now().time_since_epoch())
                   .count();
             }),
      engine_(engine),
      log_(std::move(log)),
      forwarder_(std::move(peers)),
      node_(std::move(node), log_.get(), log_.get(), log_.get(), engine) {}

ClusterMode::~ClusterMode() { Shutdown(); }

void ClusterMode::Run(std::function<void(const std::string&)> lost) {
  if (lost) node_.OnFleetLost(std::move(lost));
  node_.Start();
}

void ClusterMode::Shutdown() {
  if (shut_down_) return;
  shut_down_ = true;
  node_.Stop();
  node_.ReleaseAll();
}

absl::StatusOr<engine::UploadResult> ClusterMode::Upload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces) {
  // Checked here against the fleet's shape (from this replica's store, or
  // asked of the owner), so that an acknowledged upload is not refused when
  // the owner applies it; the owner checks it again then.
  absl::StatusOr<std::optional<engine::FleetShape>> shape = ShapeOf(fleet_id);
  if (!shape.ok()) return shape.status();
  absl::Status valid = engine_->CheckUpload(
      fleet_id, traces, shape->has_value() ? &**shape : nullptr);
  if (!valid.ok()) return valid;
  if (traces.empty()) return engine::UploadResult{};
  if (absl::Status admitted = rates_.AdmitRates(fleet_id, traces);
      !admitted.ok()) {
    return admitted;
  }
  // An upload that creates the fleet is appended only as its log's first
  // entry: of two creating it at once with different shapes, the second
  // is checked against the first's shape instead of being acknowledged
  // and refused when applied.
  absl::StatusOr<cluster::Ingested> ingested = cluster::Ingest(
      *log_, fleet_id, traces, max_entry_bytes_, !shape->has_value());
  if (absl::IsFailedPrecondition(ingested.status()) && !shape->has_value()) {
    shape = ShapeOf(fleet_id);
    if (!shape.ok()) return shape.status();
    valid = engine_->CheckUpload(fleet_id, traces,
                                 shape->has_value() ? &**shape : nullptr);
    if (!valid.ok()) return valid;
    ingested = cluster::Ingest(*log_, fleet_id, traces, max_entry_bytes_);
  }
  if (!ingested.ok()) return ingested.status();
  engine::UploadResult result;
  result.accepted = ingested->traces - ingested->duplicate_traces;
  result.duplicates = ingested->duplicate_traces;
  return result;
}

absl::StatusOr<std::optional<engine::FleetShape>> ClusterMode::ShapeOf(
    std::string_view fleet_id) {
  {
    absl::MutexLock lock(&owners_mu_);
    auto it = shapes_.find(std::string(fleet_id));
    if (it != shapes_.end()) return it->second;
  }
  absl::StatusOr<std::optional<engine::FleetShape>> shape =
      cluster::FleetShapeFromLog(*log_, log_.get(), fleet_id);
  if (!shape.ok() || !shape->has_value()) return shape;
  absl::MutexLock lock(&owners_mu_);
  shapes_[std::string(fleet_id)] = **shape;
  return shape;
}

absl::StatusOr<std::optional<std::string>> ClusterMode::Owner(
    std::string_view fleet_id) {
  if (node_.materialiser().Owns(fleet_id)) return std::nullopt;
  absl::StatusOr<std::optional<cluster::Lease>> holder = log_->Holder(fleet_id);
  if (!holder.ok()) {
    // NATS cannot say now (a JetStream leader election): the last owner
    // seen answers, or says the fleet moved.
    absl::MutexLock lock(&owners_mu_);
    auto it = last_owner_.find(std::string(fleet_id));
    if (it != last_owner_.end() && it->second != self_) return it->second;
    return holder.status();
  }
  if (holder->has_value()) {
    {
      absl::MutexLock lock(&owners_mu_);
      last_owner_[std::string(fleet_id)] = (*holder)->owner;
    }
    if ((*holder)->owner == self_) {
      // Taken by this replica's loop a moment ago.
      return std::nullopt;
    }
    return (*holder)->owner;
  }
  absl::StatusOr<uint64_t> last = log_->LastSequence(fleet_id);
  if (!last.ok()) return last.status();
  // No log: the fleet does not exist, which this replica says as well as
  // any.
  if (*last == 0) return std::nullopt;
  return absl::UnavailableError(absl::StrCat(
      "fleet \"", V(fleet_id),
      "\" has no owner right now (its owner was lost; another replica takes "
      "it once the lease expires); retry"));
}

absl::StatusOr<std::vector<std::pair<std::string, std::string>>>
ClusterMode::Fleets() {
  // While NATS cannot answer (a JetStream leader election), the last
  // listing and the last owners seen answer, as Owner does.
  absl::StatusOr<std::vector<std::string>> fleets = log_->Fleets();
  {
    absl::MutexLock lock(&owners_mu_);
    if (fleets.ok()) {
      known_fleets_ = *fleets;
    } else if (!known_fleets_.empty()) {
      fleets = known_fleets_;
    }
  }
  if (!fleets.ok()) return fleets.status();
  std::vector<std::pair<std::string, std::string>> owners;
  for (const std::string& fleet : *fleets) {
    std::string owner;
    if (node_.materialiser().Owns(fleet)) {
      owner = self_;
    } else {
      absl::StatusOr<std::optional<cluster::Lease>> holder =
          log_->Holder(fleet);
      absl::MutexLock lock(&owners_mu_);
      if (holder.ok() && holder->has_value()) {
        owner = (*holder)->owner;
        last_owner_[fleet] = owner;
      } else if (!holder.ok()) {
        auto last = last_owner_.find(fleet);
        if (last == last_owner_.end()) return holder.status();
        owner = last->second;
      }
    }
    owners.emplace_back(fleet, std::move(owner));
  }
  return owners;
}

absl::Status ClusterMode::Forward(const std::string& address,
                                  std::string_view method,
                                  const google::protobuf::Message& request,
                                  google::protobuf::Message* response) {
  return forwarder_.Forward(address, method, request, response);
}

std::vector<std::pair<std::string, double>> ClusterMode::LogLag() {
  std::vector<std::pair<std::string, double>> lag;
  for (const auto& [fleet_id, position] : node_.materialiser().Positions()) {
    absl::StatusOr<uint64_t> last = log_->LastSequence(fleet_id);
    if (!last.ok()) continue;
    lag.emplace_back(
        fleet_id, static_cast<double>(*last > position ? *last - position : 0));
  }
  return lag;
}

absl::StatusOr<engine::ConsolidateResult> ClusterMode::Consolidate(
    std::string_view fleet_id) {
  return node_.materialiser().Consolidate(fleet_id);
}

absl::StatusOr<std::vector<core::MemoryTrace>> ClusterMode::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, uint64_t count,
    std::string_view request_id) {
  return node_.materialiser().SampleReplay(fleet_id, robot_id, count,
                                           request_id);
}

}  // namespace fleetmem::server
