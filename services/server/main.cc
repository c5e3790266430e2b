// fleetmem-server: the composition root. Reads flags and the config file,
// opens RocksDB under DATA_DIR/db, loads every fleet into the engine, serves
// fleetmem.v1.MemoryService (plus health checking and reflection) with the
// credentials file's access policy and TLS when configured, re-reads the
// credentials file on SIGHUP, and shuts down cleanly on SIGTERM or SIGINT.
//
// Exit codes: 0 after a clean shutdown or --help; 2 for bad flags or config;
// 1 if the server cannot start (storage, engine, address, --ready-file).
#include <dlfcn.h>
#include <pthread.h>
#include <signal.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>
#include <system_error>
#include <thread>
#include <utility>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/synchronization/notification.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "fleetmem_version.h"
#include "grpc/health/v1/health.pb.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/health_check_service_interface.h"
#include "grpcpp/security/server_credentials.h"
#include "grpcpp/security/tls_certificate_provider.h"
#include "grpcpp/security/tls_credentials_options.h"
#include "services/auth/authenticator.h"
#include "services/common/files.h"
#include "services/common/log.h"
#include "services/common/usage.h"
#include "services/engine/fleet_aliases.h"
#include "services/engine/memory_engine.h"
#include "services/engine/write_path.h"
#include "services/http/http_server.h"
#include "services/http/rest_gateway.h"
#include "services/index/exact_index.h"
#include "services/index/flann_index.h"
#include "services/index/hnsw_index.h"
#include "services/observability/metrics.h"
#include "services/observability/process_stats.h"
#include "services/server/cluster_mode.h"
#include "services/server/reflection_v1.h"
#include "services/server/server_config.h"
#include "services/storage/rocksdb_store.h"
#include "services/transport/embedded_memory.h"
#include "services/transport/memory_api.h"
#include "services/transport/memory_service.h"
#include "services/transport/work_queue.h"

namespace fleetmem::server {
namespace {

// gRPC's reflection library registers its server plugin from a static
// initializer when it is loaded, and every server built afterwards then
// answers reflection without credentials. So it is not linked: it is loaded
// here, only where reflection is wanted (auth off, or reflection_with_auth).
bool LoadReflection() {
  if (dlopen(FLEETMEM_REFLECTION_LIBRARY, RTLD_NOW | RTLD_GLOBAL) != nullptr) {
    return true;
  }
  FLEETMEM_LOG(kWarning) << "gRPC reflection is off: "
                         << FLEETMEM_REFLECTION_LIBRARY << " cannot be loaded ("
                         << dlerror() << ")";
  return false;
}

// Runs `task` every `interval_seconds` on a thread of its own until Stop()
// (none if the interval is not positive).
class PeriodicTask {
 public:
  PeriodicTask(int interval_seconds, std::function<void()> task) {
    if (interval_seconds <= 0) return;
    const absl::Duration interval = absl::Seconds(interval_seconds);
    thread_ = std::thread([this, interval, task = std::move(task)] {
      while (!stop_.WaitForNotificationWithTimeout(interval)) task();
    });
  }
  ~PeriodicTask() { Stop(); }
  PeriodicTask(const PeriodicTask&) = delete;
  PeriodicTask& operator=(const PeriodicTask&) = delete;

  // Waits for a turn in progress, then stops.
  void Stop() {
    if (!thread_.joinable()) return;
    stop_.Notify();
    thread_.join();
  }

 private:
  absl::Notification stop_;
  std::thread thread_;
};

constexpr char kServiceName[] = "fleetmem.v1.MemoryService";

engine::PlaceIndexFactory MakeIndexFactory(const ServerConfig& config) {
  switch (config.index) {
    case IndexKind::kFlann:
      return [options = config.flann](size_t dimension) {
        return index::NewFlannIndex(dimension, options);
      };
    case IndexKind::kHnsw:
      return [options = config.tiered.hnsw](size_t dimension) {
        return index::NewHnswIndex(dimension, options);
      };
    case IndexKind::kAuto:
      return [options = config.tiered](size_t dimension) {
        return index::NewTieredIndex(dimension, options);
      };
    case IndexKind::kExact:
      break;
  }
  return [](size_t dimension) { return index::NewExactIndex(dimension); };
}

// The index of a fleet whose settings name its own kind or graph codes:
// the server's options for that kind (the server's kind when the fleet
// names only its codes), with the fleet's HNSW M, ef and codes where it
// sets them.
engine::FleetIndexFactory MakeFleetIndexFactory(const ServerConfig& config) {
  return [config](size_t dimension, const engine::IndexSettings& fleet)
             -> std::unique_ptr<engine::PlaceIndex> {
    engine::IndexSettings index = fleet;
    if (index.kind == engine::IndexSettings::Kind::kServer) {
      switch (config.index) {
        case IndexKind::kHnsw:
          index.kind = engine::IndexSettings::Kind::kHnsw;
          break;
        case IndexKind::kAuto:
          index.kind = engine::IndexSettings::Kind::kAuto;
          break;
        case IndexKind::kExact:
        case IndexKind::kFlann:
          return MakeIndexFactory(config)(dimension);
      }
    }
    index::TieredIndexOptions options = config.tiered;
    if (index.hnsw_m > 0) options.hnsw.m = static_cast<size_t>(index.hnsw_m);
    if (index.hnsw_ef_search > 0) {
      options.hnsw.ef_search = static_cast<size_t>(index.hnsw_ef_search);
    }
    if (index.hnsw_codes == engine::IndexSettings::Codes::kInt8) {
      options.hnsw.codes = index::HnswIndexOptions::Codes::kInt8;
    }
    if (index.hnsw_codes == engine::IndexSettings::Codes::kFloat) {
      options.hnsw.codes = index::HnswIndexOptions::Codes::kFloat;
    }
    switch (index.kind) {
      case engine::IndexSettings::Kind::kHnsw:
        return index::NewHnswIndex(dimension, options.hnsw);
      case engine::IndexSettings::Kind::kAuto:
        return index::NewTieredIndex(dimension, options);
      case engine::IndexSettings::Kind::kExact:
      case engine::IndexSettings::Kind::kServer:
        break;
    }
    return index::NewExactIndex(dimension);
  };
}

// "host:port" with the port replaced by `port` (for listen port 0).
std::string WithPort(const std::string& listen, int port) {
  return listen.substr(0, listen.rfind(':') + 1) + std::to_string(port);
}

http::HttpServerOptions HttpOptions(const ServerConfig& config) {
  http::HttpServerOptions options;
  options.listen = config.http_listen;
  options.tls_cert_file = config.security.tls_cert_file;
  options.tls_key_file = config.security.tls_key_file;
  options.tls_client_ca_file = config.security.tls_client_ca_file;
  options.require_client_certificate =
      config.security.require_client_certificate;
  options.max_body_bytes = config.max_http_body_bytes;
  options.connections.max_connections = config.http_max_connections;
  options.connections.max_connections_per_client =
      config.http_max_connections_per_client;
  options.connections.head_timeout =
      absl::Seconds(config.http_head_timeout_seconds);
  // Logged at most every 10 s (a flood of slow clients must not flood the
  // log), with the count since the last line.
  struct Refusals {
    absl::Mutex mu;
    absl::Time logged = absl::InfinitePast();
    uint64_t unlogged = 0;
  };
  options.connections.on_refused =
      [refusals = std::make_shared<Refusals>()](const std::string& why) {
        absl::MutexLock lock(&refusals->mu);
        ++refusals->unlogged;
        if (absl::Now() - refusals->logged < absl::Seconds(10)) return;
        FLEETMEM_LOG(kWarning) << refusals->unlogged
                               << " HTTP connection(s) refused or closed by a "
                                  "limit since the last report; the latest: "
                               << why;
        refusals->unlogged = 0;
        refusals->logged = absl::Now();
      };
  options.version = FLEETMEM_VERSION;
  return options;
}

// Blocks SIGTERM, SIGINT and SIGHUP in this thread and every thread it
// starts later (gRPC's, RocksDB's, the workers), so that only sigwait sees
// them.
sigset_t BlockShutdownSignals() {
  sigset_t signals;
  sigemptyset(&signals);
  sigaddset(&signals, SIGTERM);
  sigaddset(&signals, SIGINT);
  sigaddset(&signals, SIGHUP);
  pthread_sigmask(SIG_BLOCK, &signals, nullptr);
  return signals;
}

absl::StatusOr<std::vector<auth::CredentialEntry>> ReadCredentials(
    const std::string& path) {
  absl::StatusOr<std::string> text = files::ReadFile(path);
  if (!text.ok()) {
    return absl::Status(
        text.status().code(),
        absl::StrCat("credentials file ", path, ": cannot be read"));
  }
  absl::StatusOr<std::vector<auth::CredentialEntry>> entries =
      auth::ParseCredentials(*text);
  if (!entries.ok()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "credentials file ", path, ": ", entries.status().message()));
  }
  return entries;
}

// INVALID_ARGUMENT naming the first TLS file that cannot be read.
absl::Status CheckReadable(const SecurityConfig& security) {
  for (const std::string* path :
       {&security.tls_cert_file, &security.tls_key_file,
        &security.tls_client_ca_file}) {
    if (path->empty()) continue;
    std::ifstream in(*path);
    if (!in) {
      return absl::InvalidArgumentError(
          absl::StrCat("TLS file ", *path, ": cannot be read"));
    }
  }
  return absl::OkStatus();
}

// Plaintext, or TLS from files that gRPC re-reads every tls_reload_seconds
// (so a renewed certificate is served without a restart).
std::shared_ptr<grpc::ServerCredentials> MakeServerCredentials(
    const SecurityConfig& security) {
  if (security.tls_cert_file.empty()) {
    return grpc::InsecureServerCredentials();
  }
  auto provider =
      std::make_shared<grpc::experimental::FileWatcherCertificateProvider>(
          security.tls_key_file, security.tls_cert_file,
          security.tls_client_ca_file,
          static_cast<unsigned int>(security.tls_reload_seconds));
  grpc::experimental::TlsServerCredentialsOptions options(provider);
  options.watch_identity_key_cert_pairs();
  if (security.tls_client_ca_file.empty()) {
    options.set_cert_request_type(GRPC_SSL_DONT_REQUEST_CLIENT_CERTIFICATE);
  } else {
    options.watch_root_certs();
    options.set_cert_request_type(
        security.require_client_certificate
            ? GRPC_SSL_REQUEST_AND_REQUIRE_CLIENT_CERTIFICATE_AND_VERIFY
            : GRPC_SSL_REQUEST_CLIENT_CERTIFICATE_AND_VERIFY);
  }
  return grpc::experimental::TlsServerCredentials(options);
}

// Re-reads the credentials file; a file that does not load leaves the old
// credentials in force.
void ReloadCredentials(const std::string& path,
                       auth::Authenticator* authenticator) {
  if (authenticator == nullptr) {
    FLEETMEM_LOG(kInfo) << "SIGHUP: auth is off, nothing to reload";
    return;
  }
  absl::StatusOr<std::vector<auth::CredentialEntry>> entries =
      ReadCredentials(path);
  if (!entries.ok()) {
    FLEETMEM_LOG(kError) << "SIGHUP: keeping the previous credentials: "
                         << entries.status().message();
    return;
  }
  const size_t count = entries->size();
  authenticator->Replace(std::move(*entries));
  FLEETMEM_LOG(kInfo) << "SIGHUP: reloaded " << count << " principals from "
                      << path;
}

// Writes the --ready-file (ServerConfig::ready_file): a temporary file
// beside it, synced, then renamed over it, so a reader sees all of it or
// nothing.
absl::Status WriteReadyFile(const std::string& path,
                            const std::string& grpc_address,
                            const std::string& http_address) {
  std::string text = absl::StrCat("grpc=", grpc_address, "\n");
  if (!http_address.empty())
    absl::StrAppend(&text, "http=", http_address, "\n");
  absl::StrAppend(&text, "pid=", getpid(), "\n");
  const std::string temporary = absl::StrCat(path, ".tmp");
  {
    std::ofstream out(temporary, std::ios::trunc);
    out << text;
    out.flush();
    if (!out) {
      return absl::InternalError(
          absl::StrCat("ready file: cannot write ", temporary));
    }
  }
  std::error_code error;
  std::filesystem::rename(temporary, path, error);
  if (error) {
    std::filesystem::remove(temporary, error);
    return absl::InternalError(absl::StrCat("ready file: cannot rename ",
                                            temporary, " to ", path, ": ",
                                            error.message()));
  }
  return absl::OkStatus();
}

// Removes the --ready-file if there is one (a missing file is fine).
void RemoveReadyFile(const std::string& path) {
  if (path.empty()) return;
  std::error_code error;
  std::filesystem::remove(path, error);
  if (error) {
    FLEETMEM_LOG(kWarning) << "ready file " << path
                           << ": cannot remove: " << error.message();
  }
}

// One run of the server, from taking the data directory to the last index
// snapshot. Its parts are members in the order they are made, so that a
// start that fails part way tears down what was made in reverse; each step
// returns 0 to go on, or the process's exit code (the cause logged).
class ServerRun {
 public:
  explicit ServerRun(const ServerConfig& config)
      : config_(config), security_(config.security) {}
  ServerRun(const ServerRun&) = delete;
  ServerRun& operator=(const ServerRun&) = delete;

  // The data directory (made if missing, locked against a second server;
  // refused if it is a snapshot; filled from --restore-from), the
  // credentials, the store with its log, and every fleet loaded.
  int OpenData();
  // --restore-from: the snapshot's db/ copied into the (new) data dir.
  int RestoreSnapshot();
  // hnsw { floats: "file" }: the graphs' floats directory made, and what a
  // crash left in it (a file made and not yet unlinked) removed; 1 (logged)
  // when it cannot be made.
  int PrepareGraphFloats();
  // The background tasks, the work queue and the mode: embedded (uploads
  // acknowledged at the durable append to each fleet's log, applied behind
  // it: engine::WritePath) or distributed (this replica materialises the
  // fleets it owns from their replicated logs and routes every other
  // fleet's calls to its owner); then the service over it.
  int StartMode();
  // StartMode's two modes: memory_ and the metrics' sources for each.
  int StartDistributed();
  int StartEmbedded();
  // The gRPC port, with health checking and (where allowed) reflection.
  int StartGrpc();
  // The HTTP port: the service's MemoryApi behind the REST gateway, the
  // dashboard, /metrics and the probes (none without http_listen).
  int StartHttp();
  // Logs what serves where and how, and the distributed mode's ownership
  // loop starts; then the ready file announces the server. 1 if it cannot
  // be written (whoever started the server waits for it).
  int Announce();
  // Until SIGTERM or SIGINT; SIGHUP re-reads the credentials file.
  void WaitForShutdownSignal(const sigset_t& signals);
  // New calls refused, running ones given the grace period, what was
  // acknowledged applied if it can be meanwhile, the indexes saved.
  void ShutDown();
  // After a failed step: the ports and the work queue stop at once.
  void StopEarly();

 private:
  const ServerConfig& config_;
  const SecurityConfig& security_;
  std::unique_ptr<files::DirectoryLock> data_dir_lock_;
  std::unique_ptr<auth::Authenticator> authenticator_;
  std::string store_path_;
  // Metrics observe the store, the log, the engine and both transports
  // through hooks (services/observability).
  observability::Metrics metrics_;
  std::unique_ptr<engine::FleetLog> log_;
  std::unique_ptr<engine::MemoryStore> store_;
  std::unique_ptr<engine::MemoryEngine> engine_;
  std::unique_ptr<PeriodicTask> snapshotter_;
  std::unique_ptr<PeriodicTask> heap_trimmer_;
  std::unique_ptr<PeriodicTask> retention_;
  std::unique_ptr<transport::WorkQueue> work_;
  transport::ServiceOptions service_options_;
  // The mode, chosen once (services/transport/fleet_memory.h).
  std::unique_ptr<cluster::ReplicatedMemory> replicated_;
  std::unique_ptr<engine::StoredAliases> aliases_;  // embedded mode's
  std::unique_ptr<transport::EmbeddedMemory> embedded_;
  transport::FleetMemory* memory_ = nullptr;
  std::unique_ptr<transport::MemoryServiceImpl> service_;
  bool reflection_ = false;
  std::unique_ptr<ReflectionV1> reflection_v1_;
  int port_ = 0;
  std::unique_ptr<grpc::Server> server_;
  std::atomic<bool> ready_{true};
  std::unique_ptr<http::RestGateway> gateway_;
  std::unique_ptr<http::HttpServer> http_server_;
  std::string http_address_;
};

// A snapshot is a backup: a server on it would make it a live store (its
// lock and reserve files, then new writes). Refused (logged) before anything
// in it changes; --restore-from copies it into a new data dir instead.
bool IsSnapshot(const std::string& data_dir) {
  std::error_code error;
  if (!std::filesystem::exists(
          std::filesystem::path(data_dir) / transport::kSnapshotMarker,
          error)) {
    return false;
  }
  FLEETMEM_LOG(kError) << "data dir " << data_dir << " is a snapshot (it holds "
                       << transport::kSnapshotMarker
                       << "): a server on it would turn the backup into a "
                          "live store; restore it into a new data dir "
                          "instead: fleetmem-server --data-dir NEW_DIR "
                          "--restore-from "
                       << data_dir << " (nothing was changed)";
  return true;
}

int ServerRun::PrepareGraphFloats() {
  namespace fs = std::filesystem;
  const std::string& directory = config_.tiered.hnsw.floats_dir;
  if (directory.empty()) return 0;
  std::error_code error;
  fs::create_directories(directory, error);
  if (error) {
    FLEETMEM_LOG(kError) << "cannot create " << directory
                         << " (hnsw floats \"file\"): " << error.message();
    return 1;
  }
  for (const fs::directory_entry& entry :
       fs::directory_iterator(directory, error)) {
    if (entry.path().filename().string().rfind("graph-floats-", 0) == 0) {
      fs::remove(entry.path(), error);
    }
  }
  return 0;
}

int ServerRun::RestoreSnapshot() {
  namespace fs = std::filesystem;
  std::error_code error;
  const fs::path from = fs::path(config_.restore_from) / "db";
  const fs::path to = fs::path(config_.data_dir) / "db";
  if (fs::exists(to, error) && !fs::is_empty(to, error)) {
    FLEETMEM_LOG(kError) << "--restore-from: data dir " << config_.data_dir
                         << " holds a store already (" << to.string()
                         << "); a restore fills only a new data dir "
                            "(nothing restored, nothing changed)";
    return 2;
  }
  // Copied beside, then renamed into place: a copy cut short (a full disk,
  // a kill) never leaves a partial store where the server looks.
  const fs::path copying = fs::path(config_.data_dir) / "db.restoring";
  fs::remove_all(copying, error);
  fs::remove(to, error);  // an empty db/ left by an earlier attempt
  fs::copy(from, copying, fs::copy_options::recursive, error);
  if (!error) fs::rename(copying, to, error);
  if (error) {
    std::error_code ignored;
    fs::remove_all(copying, ignored);
    FLEETMEM_LOG(kError) << "--restore-from " << config_.restore_from
                         << ": cannot copy its db/ into " << to.string() << ": "
                         << error.message() << "; nothing restored";
    return 1;
  }
  FLEETMEM_LOG(kInfo) << "restored snapshot " << config_.restore_from
                      << " into " << to.string()
                      << " (the snapshot is unchanged)";
  return 0;
}

int ServerRun::OpenData() {
  if (IsSnapshot(config_.data_dir)) return 2;
  // A --restore-from that is no snapshot: refused before the data dir is
  // made (nothing is created for a restore that cannot happen).
  if (!config_.restore_from.empty() &&
      !std::filesystem::is_directory(
          std::filesystem::path(config_.restore_from) / "db")) {
    FLEETMEM_LOG(kError) << "--restore-from " << config_.restore_from
                         << ": not a snapshot (no db/ in it); nothing "
                            "restored, nothing changed";
    return 2;
  }
  std::error_code error;
  std::filesystem::create_directories(config_.data_dir, error);
  if (error) {
    FLEETMEM_LOG(kError) << "cannot create data dir " << config_.data_dir
                         << ": " << error.message();
    return 1;
  }
  // One server per data directory, taken before anything is changed (the
  // ready file, the store's reserve file): a second server exits here.
  absl::StatusOr<std::unique_ptr<files::DirectoryLock>> lock =
      files::DirectoryLock::Take(config_.data_dir, "fleetmem-server.lock");
  if (!lock.ok()) {
    FLEETMEM_LOG(kError) << "cannot use data dir: " << lock.status().message();
    return 1;
  }
  data_dir_lock_ = *std::move(lock);
  if (const int floats = PrepareGraphFloats(); floats != 0) return floats;
  if (!config_.restore_from.empty()) {
    if (const int restored = RestoreSnapshot(); restored != 0) return restored;
  }
  // A ready file from an earlier run must not announce this one.
  RemoveReadyFile(config_.ready_file);
  if (!security_.auth_file.empty()) {
    absl::StatusOr<std::vector<auth::CredentialEntry>> entries =
        ReadCredentials(security_.auth_file);
    if (!entries.ok()) {
      FLEETMEM_LOG(kError) << entries.status().message();
      return 2;
    }
    authenticator_ = std::make_unique<auth::Authenticator>(std::move(*entries));
  }
  if (absl::Status readable = CheckReadable(security_); !readable.ok()) {
    FLEETMEM_LOG(kError) << readable.message();
    return 2;
  }
  storage::RocksDbStoreOptions store_options = config_.storage;
  store_options.path =
      (std::filesystem::path(config_.data_dir) / "db").string();
  store_path_ = store_options.path;
  // Distributed mode: the log is the durable copy (ClusterConfig::sync_store).
  if (config_.cluster.enabled())
    store_options.sync = config_.cluster.sync_store;
  absl::StatusOr<storage::LocalStorage> opened =
      storage::OpenLocalStorage(store_options);
  if (!opened.ok()) {
    FLEETMEM_LOG(kError) << "cannot open store: " << opened.status();
    return 1;
  }
  log_ = metrics_.TimedLog(opened->log);
  store_ = metrics_.TimedStore(std::move(opened->store));
  // Upload rates are checked where an upload is appended (the write path,
  // or the receiving replica); the engine applies log entries unrated.
  // Replicas must draw a logged sample alike (EngineOptions).
  engine::EngineOptions engine_options = config_.engine;
  engine_options.draw_in_memory_order = config_.cluster.enabled();
  engine_options.fleet_index_factory = MakeFleetIndexFactory(config_);
  absl::StatusOr<std::unique_ptr<engine::MemoryEngine>> engine =
      engine::MemoryEngine::Open(engine_options, store_.get(),
                                 MakeIndexFactory(config_),
                                 metrics_.EngineHooks());
  if (!engine.ok()) {
    FLEETMEM_LOG(kError) << "cannot load fleets: " << engine.status();
    return 1;
  }
  engine_ = *std::move(engine);
  return 0;
}

int ServerRun::StartMode() {
  // Index snapshots while serving: every interval the fleets whose index
  // changed (and holds at least index_snapshot_min_codes codes) save one, so
  // that a restart after a crash re-adds only the traces stored since
  // instead of rebuilding every graph. Errors are logged by the engine; the
  // next turn tries again.
  snapshotter_ = std::make_unique<PeriodicTask>(
      config_.index_snapshot_interval_seconds,
      [engine = engine_.get(), min_codes = config_.index_snapshot_min_codes] {
        engine
            ->SaveIndexSnapshots({.min_codes = min_codes, .only_changed = true})
            .IgnoreError();
      });
  // The heap's free pages back to the system (docs/reliability.md, "Soak").
  heap_trimmer_ = std::make_unique<PeriodicTask>(
      config_.heap_trim_interval_seconds, observability::TrimHeap);
  work_ = std::make_unique<transport::WorkQueue>(config_.work);
  service_options_ = config_.service;
  service_options_.api.snapshot_root =
      config_.snapshot_dir.empty()
          ? (std::filesystem::path(config_.data_dir) / "snapshots").string()
          : config_.snapshot_dir;
  service_options_.on_call = [this](std::string_view transport,
                                    std::string_view method,
                                    absl::StatusCode code, double seconds) {
    metrics_.ObserveCall(transport, method, code, seconds);
  };
  service_options_.on_upload_bytes = [this](std::string_view fleet,
                                            size_t bytes) {
    metrics_.ObserveUploadBytes(fleet, bytes);
  };
  service_options_.api.on_upload_bytes = service_options_.on_upload_bytes;
  const int started =
      config_.cluster.enabled() ? StartDistributed() : StartEmbedded();
  if (started != 0) return started;
  // Retention through the fleets' logs, as of this server's clock.
  retention_ = std::make_unique<PeriodicTask>(
      config_.retention_interval_seconds,
      [engine = engine_.get(), memory = memory_] {
        transport::EnforceRetention(*engine, *memory,
                                    absl::ToUnixNanos(absl::Now()));
      });
  service_ = std::make_unique<transport::MemoryServiceImpl>(
      engine_.get(), memory_, work_.get(), authenticator_.get(),
      service_options_);
  return 0;
}

int ServerRun::StartDistributed() {
  absl::StatusOr<std::unique_ptr<cluster::ReplicatedMemory>> started =
      StartClusterMode(config_, engine_.get());
  if (!started.ok()) {
    FLEETMEM_LOG(kError) << "cluster: " << started.status();
    return 1;
  }
  replicated_ = *std::move(started);
  memory_ = replicated_.get();
  // Each fleet's gauges come from the replica that serves it.
  cluster::ReplicatedMemory* serving = replicated_.get();
  metrics_.SetScrapeSources(
      {engine_.get(), store_.get(), [this] { return work_->queued(); },
       [serving](const std::string& fleet) { return serving->Serves(fleet); },
       [serving] { return serving->LogLag(); },
       [serving] { return serving->FleetCounts(); }, nullptr});
  return 0;
}

int ServerRun::StartEmbedded() {
  // Duplicates are found at the append (the apply meets none): counted
  // by the same metric as the engine's.
  engine::WritePathOptions write_path = config_.write_path;
  write_path.on_duplicates = [on_upload = metrics_.EngineHooks().on_upload](
                                 std::string_view fleet, uint64_t duplicates) {
    engine::UploadResult result;
    result.duplicates = duplicates;
    if (on_upload) on_upload(fleet, result);
  };
  absl::StatusOr<std::unique_ptr<engine::StoredAliases>> aliases =
      engine::StoredAliases::Open(store_.get());
  if (!aliases.ok()) {
    FLEETMEM_LOG(kError) << "cannot read the fleet aliases: "
                         << aliases.status();
    return 1;
  }
  aliases_ = *std::move(aliases);
  absl::StatusOr<std::unique_ptr<transport::EmbeddedMemory>> opened =
      transport::EmbeddedMemory::Open(
          engine_.get(), log_.get(),
          {.write_path = write_path,
           .max_apply_wait = config_.write_path_max_apply_wait,
           .aliases = aliases_.get()});
  if (!opened.ok()) {
    FLEETMEM_LOG(kError) << "cannot recover the fleets' logs: "
                         << opened.status();
    return 1;
  }
  embedded_ = *std::move(opened);
  memory_ = embedded_.get();
  engine::WritePath* writes = &embedded_->writes();
  observability::ScrapeSources sources;
  sources.engine = engine_.get();
  sources.store = store_.get();
  sources.work_queue_depth = [this] { return work_->queued(); };
  sources.backlogs = [writes] { return writes->Backlogs(); };
  metrics_.SetScrapeSources(std::move(sources));
  return 0;
}

int ServerRun::StartGrpc() {
  grpc::EnableDefaultHealthCheckService(true);
  // gRPC's default health service has no C++ descriptor of its own:
  // grpc.health.v1's generated code (proto/grpc/health/v1) puts health.proto
  // into the descriptor pool, so that reflection can describe the service
  // (grpcurl ... grpc.health.v1.Health/Check without -proto).
  (void)grpc::health::v1::HealthCheckRequest::descriptor();
  reflection_ = (authenticator_ == nullptr || security_.reflection_with_auth) &&
                LoadReflection();
  grpc::ServerBuilder builder;
  builder.AddListeningPort(config_.listen, MakeServerCredentials(security_),
                           &port_);
  builder.SetMaxReceiveMessageSize(
      static_cast<int>(config_.max_receive_message_bytes));
  // Clients ping every 20 s to notice dead paths (ClientOptions::
  // keepalive_time); gRPC's default answers a ping more often than every
  // 5 minutes with GOAWAY "too_many_pings". Accept one every 10 s, also
  // without calls; the server pings idle connections every 2 hours itself.
  builder.AddChannelArgument(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  builder.AddChannelArgument(
      GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS, 10000);
  // gRPC sets SO_REUSEPORT by default: a second server on a port in use
  // then started, and the kernel split calls between the two.
  builder.AddChannelArgument(GRPC_ARG_ALLOW_REUSEPORT, 0);
  builder.RegisterService(service_.get());
  // v1 beside the library's v1alpha, where reflection is served at all.
  if (reflection_) {
    reflection_v1_ = std::make_unique<ReflectionV1>(
        std::vector<std::string>{kServiceName, "grpc.health.v1.Health",
                                 "grpc.reflection.v1alpha.ServerReflection",
                                 "grpc.reflection.v1.ServerReflection"});
    builder.RegisterService(reflection_v1_.get());
  }
  server_ = builder.BuildAndStart();
  if (server_ == nullptr || port_ == 0) {
    FLEETMEM_LOG(kError) << "cannot listen on " << config_.listen
                         << " (is another process listening there?)";
    return 1;
  }
  grpc::HealthCheckServiceInterface* health = server_->GetHealthCheckService();
  health->SetServingStatus(kServiceName, true);
  health->SetServingStatus(true);
  return 0;
}

int ServerRun::StartHttp() {
  if (config_.http_listen.empty()) return 0;
  // /readyz names lost log entries and logs that cannot be applied.
  std::function<std::vector<std::string>()> ready_warnings;
  if (embedded_ != nullptr) {
    ready_warnings = [writes = &embedded_->writes()] {
      return engine::BacklogWarnings(writes->Backlogs());
    };
  }
  absl::StatusOr<std::unique_ptr<http::RestGateway>> made =
      http::RestGateway::Create(
          &service_->api(), authenticator_.get(), service_options_.on_call,
          {.max_body_bytes = config_.max_http_body_bytes,
           .loopback_hosts_only = authenticator_ == nullptr &&
                                  IsLoopbackListen(config_.http_listen),
           .allowed_origins = config_.http_allowed_origins,
           // While an answer is built it is held twice (the engine's copy
           // of the traces, then the message).
           .max_answer_bytes = 2 * config_.engine.max_read_bytes});
  absl::StatusOr<std::unique_ptr<http::HttpServer>> started =
      made.ok() ? http::HttpServer::Start(
                      HttpOptions(config_),
                      {made->get(), [this] { return metrics_.Render(); },
                       [this] { return ready_.load(); },
                       security_.metrics_without_auth, ready_warnings})
                : made.status();
  if (!started.ok()) {
    FLEETMEM_LOG(kError) << "HTTP: " << started.status().message();
    return started.status().code() == absl::StatusCode::kInvalidArgument ? 2
                                                                         : 1;
  }
  gateway_ = *std::move(made);
  http_server_ = *std::move(started);
  http_address_ = WithPort(config_.http_listen, http_server_->port());
  FLEETMEM_LOG(kInfo) << "HTTP on " << http_address_ << " (dashboard at /, "
                      << "REST under /v1/, /metrics, /healthz, /readyz)";
  std::cout << "fleetmem-server http on " << http_address_ << std::endl;
  return 0;
}

int ServerRun::Announce() {
  const std::string address = WithPort(config_.listen, port_);
  FLEETMEM_LOG(kInfo) << "data dir " << config_.data_dir << " (store "
                      << store_path_ << "), " << engine_->ListFleets().size()
                      << " fleets loaded";
  FLEETMEM_LOG(kInfo) << "options: " << DescribeConfig(config_);
  if (authenticator_ == nullptr) {
    FLEETMEM_LOG(kWarning)
        << "auth is OFF: every caller may read and write every fleet "
           "(start with --auth-file FILE to require credentials)";
  } else {
    FLEETMEM_LOG(kInfo) << "auth on: " << authenticator_->size()
                        << " principals from " << security_.auth_file
                        << "; reflection "
                        << (reflection_ ? "on (without credentials)" : "off");
  }
  if (security_.tls_cert_file.empty()) {
    FLEETMEM_LOG(kWarning) << "TLS is off: traffic, tokens included, is "
                              "plaintext";
  } else {
    FLEETMEM_LOG(kInfo) << "TLS on: certificate " << security_.tls_cert_file
                        << ", re-read every " << security_.tls_reload_seconds
                        << " s";
  }
  if (replicated_ != nullptr) {
    replicated_->Run([service = service_.get()](const std::string& fleet) {
      FLEETMEM_LOG(kInfo) << "cluster: fleet \"" << fleet
                          << "\" is no longer owned here";
      service->EndWatches(fleet);
    });
    FLEETMEM_LOG(kInfo) << "cluster: replica " << config_.cluster.advertise
                        << " on NATS "
                        << absl::StrJoin(config_.cluster.nats.servers, ",")
                        << " (lease " << config_.cluster.nats.lease_ttl << ", "
                        << config_.cluster.nats.replicas
                        << " copies of each log)";
  }
  FLEETMEM_LOG(kInfo) << "fleetmem-server listening on " << address;
  std::cout << "fleetmem-server listening on " << address << std::endl;
  if (config_.ready_file.empty()) return 0;
  absl::Status written =
      WriteReadyFile(config_.ready_file, address, http_address_);
  if (written.ok()) return 0;
  // Whoever started the server waits for the file: stop rather than serve
  // unannounced.
  FLEETMEM_LOG(kError) << written.message() << "; shutting down";
  return 1;
}

void ServerRun::WaitForShutdownSignal(const sigset_t& signals) {
  int signal = 0;
  while (true) {
    sigwait(&signals, &signal);
    if (signal != SIGHUP) break;
    ReloadCredentials(security_.auth_file, authenticator_.get());
  }
  FLEETMEM_LOG(kInfo) << "received "
                      << (signal == SIGINT ? "SIGINT" : "SIGTERM")
                      << ", shutting down (grace "
                      << config_.shutdown_grace_seconds << " s)";
}

void ServerRun::ShutDown() {
  RemoveReadyFile(config_.ready_file);
  grpc::HealthCheckServiceInterface* health = server_->GetHealthCheckService();
  health->SetServingStatus(kServiceName, false);
  health->SetServingStatus(false);
  ready_.store(false);
  service_->Shutdown();  // new calls UNAVAILABLE, watches end
  retention_->Stop();
  // Calls being worked on get the grace period; then everything left (idle
  // connections, upload streams waiting on their client) is cancelled at
  // once instead of waiting for each client's GOAWAY ping acknowledgement.
  const absl::Duration grace = absl::Seconds(config_.shutdown_grace_seconds);
  if (!service_->WaitIdle(absl::Now() + grace)) {
    FLEETMEM_LOG(kWarning) << "calls still running after the grace period "
                              "are cancelled";
  }
  if (gateway_ != nullptr) gateway_->Shutdown();      // ends watches over HTTP
  if (http_server_ != nullptr) http_server_->Stop();  // finishes its calls
  server_->Shutdown(std::chrono::system_clock::now());
  work_->Stop();
  server_.reset();
  // The other replicas take this one's fleets at once.
  if (replicated_ != nullptr) replicated_->Shutdown();
  // What was acknowledged is applied now if it can be within the grace
  // period; the rest stays in the logs for the next start.
  if (embedded_ != nullptr) {
    embedded_->writes().Drain(absl::Now() + grace);
    embedded_.reset();
  }
  // Nothing changes memory any more: the next start loads the place
  // indexes instead of rebuilding them (a failure only costs that), and
  // their clusters from the snapshots' memory images instead of reading
  // every trace. Fleets whose snapshot is current for both are not written
  // again.
  snapshotter_->Stop();
  heap_trimmer_->Stop();
  engine_
      ->SaveIndexSnapshots({.only_changed = true, .refresh_memory_image = true})
      .IgnoreError();
  engine_.reset();
  store_.reset();
  FLEETMEM_LOG(kInfo) << "stopped";
}

void ServerRun::StopEarly() {
  if (server_ != nullptr) server_->Shutdown(std::chrono::system_clock::now());
  if (work_ != nullptr) work_->Stop();
}

int Serve(const ServerConfig& config, const sigset_t& signals) {
  ServerRun run(config);
  int code = 0;
  for (int (ServerRun::*step)() :
       {&ServerRun::OpenData, &ServerRun::StartMode, &ServerRun::StartGrpc,
        &ServerRun::StartHttp}) {
    if (code = (run.*step)(); code != 0) {
      run.StopEarly();
      return code;
    }
  }
  code = run.Announce();
  if (code == 0) run.WaitForShutdownSignal(signals);
  run.ShutDown();
  return code;
}

}  // namespace
}  // namespace fleetmem::server

int main(int argc, char** argv) {
  namespace server = fleetmem::server;
  const sigset_t signals = server::BlockShutdownSignals();
  absl::StatusOr<server::CommandLine> command_line =
      server::ParseCommandLine(argc, argv);
  if (!command_line.ok()) {
    std::cerr << fleetmem::common::UsageErrorText(
        "fleetmem-server", std::string(command_line.status().message()));
    return fleetmem::common::kExitUsage;
  }
  if (command_line->help) {
    std::cout << server::Usage();
    return 0;
  }
  if (command_line->version) {
    std::cout << fleetmem::common::VersionLine("fleetmem-server");
    return 0;
  }
  absl::StatusOr<server::ServerConfig> config =
      server::LoadServerConfig(*command_line);
  if (!config.ok()) {
    std::cerr << "fleetmem-server: " << config.status().message() << "\n";
    return 2;
  }
  fleetmem::log::SetLevel(config->log_level);
  return server::Serve(*config, signals);
}
