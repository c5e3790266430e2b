// fleetmem-server's settings: defaults, the command line, the config file
// (protobuf text format of server_config.proto) and their validation. Flags
// override the file, the file overrides the defaults.
#ifndef FLEETMEM_SERVICES_SERVER_SERVER_CONFIG_H_
#define FLEETMEM_SERVICES_SERVER_SERVER_CONFIG_H_

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "services/cluster/nats_fleet_log.h"
#include "services/common/log.h"
#include "services/engine/memory_engine.h"
#include "services/index/flann_index.h"
#include "services/index/hnsw_index.h"
#include "services/storage/rocksdb_store.h"
#include "services/transport/service_state.h"
#include "services/transport/work_queue.h"

namespace fleetmem::server {

enum class IndexKind { kAuto, kExact, kHnsw, kFlann };

// The place index used when neither file nor flag names one: exact (recall
// 1) while a fleet is small, HNSW from tiered.hnsw_from traces on, where the
// exact scan grows slower than the graph at the recall docs/performance.md
// states.
inline constexpr IndexKind kDefaultIndex = IndexKind::kAuto;

// "auto" / "exact" / "hnsw" / "flann"; false for anything else.
bool ParseIndexKind(std::string_view text, IndexKind* kind);
std::string_view IndexKindName(IndexKind kind);

// Identity, roles and TLS (docs/security.md).
struct SecurityConfig {
  // Credentials file (services/auth/credentials.proto); empty turns auth
  // off: every caller is an admin. Re-read on SIGHUP.
  std::string auth_file;
  // Without auth_file the server starts only on a loopback address unless
  // this is set.
  bool allow_unauthenticated = false;
  // PEM certificate chain and key of the server: TLS on when both are set.
  std::string tls_cert_file;
  std::string tls_key_file;
  // PEM CA bundle for client certificates: with it, clients may present a
  // certificate (mutual TLS) whose common name names their principal.
  std::string tls_client_ca_file;
  // Refuse TLS clients without a valid certificate (needs the client CA).
  bool require_client_certificate = false;
  // How often the certificate and key files are checked for changes.
  int tls_reload_seconds = 60;
  // Server reflection with auth on (off by default then: reflection would be
  // answered without credentials). Without auth it is always on.
  bool reflection_with_auth = false;
  // With auth on, /metrics needs a principal's credentials (any role) unless
  // this is set (a scraper on a private network that sends no token).
  bool metrics_without_auth = false;
};

// Distributed mode (docs/distributed.md); off when nats.servers is empty.
struct ClusterConfig {
  // servers, credentials, TLS, replicas, lease_ttl; nats.servers empty =
  // the embedded mode.
  cluster::NatsOptions nats;
  // HOST:PORT the other replicas reach this one at; its replica id.
  std::string advertise;
  // Between two rounds of the ownership loop.
  absl::Duration round_interval = absl::Milliseconds(200);
  // At start, how long NATS is retried while it cannot be reached or its
  // JetStream is not ready (a cluster still electing its leader).
  absl::Duration connect_timeout = absl::Seconds(60);
  // Largest log entry (under NATS's max_payload, 1 MiB by default).
  size_t max_entry_bytes = size_t{512} << 10;
  // File with the NAME:SECRET token replicas present to each other.
  std::string peer_token_file;
  // CA bundle of the other replicas' certificates (default: the client CA).
  std::string peer_ca_file;
  // The name the other replicas' certificates are issued for, when it is
  // not the host of their address (e.g. "fleetmem-server" for every pod).
  std::string peer_tls_server_name;
  // Whether the replica's own store syncs each write. Off by default: the
  // log is the durable copy, and the store keeps each write's log position
  // with it, so a replica that loses its last writes in a crash of its
  // machine re-applies them from the log (RocksDB recovers a consistent
  // prefix of its write-ahead log). Replaces storage.sync in this mode.
  bool sync_store = false;
  // The owner of a fleet stores a snapshot of it in JetStream every this
  // many log entries (0: never; a new owner then replays the whole log).
  uint64_t snapshot_every_entries = 250;
  // Whether the log entries a stored snapshot covers are removed from the
  // log (JetStream purge), so that logs stay bounded.
  bool trim_log = true;
  // Whether fleets are spread over the live replicas (a joining replica
  // gets its share; cluster::ClusterNodeOptions::balance).
  bool balance_fleets = true;

  bool enabled() const { return !nats.servers.empty(); }
};

struct ServerConfig {
  // HOST:PORT to listen on; port 0 picks a free port.
  std::string listen = "127.0.0.1:50051";
  // Folder of the server's state, created if missing; required.
  std::string data_dir;
  log::Level log_level = log::Level::kInfo;
  // Place index of every fleet.
  IndexKind index = kDefaultIndex;
  // Used when index is kFlann.
  index::FlannIndexOptions flann;
  // Used when index is kAuto (kHnsw: its `hnsw` member).
  index::TieredIndexOptions tiered;
  // int8 graphs keep their codes' floats in files of their own in
  // data_dir/graph-floats (the page cache's memory, not the process's;
  // index::HnswIndexOptions::floats_dir, set from this at startup) rather
  // than on the heap (false). Config `hnsw { floats: "file" | "memory" }`.
  bool graph_floats_in_files = true;
  // Memory parameters and limits of the engine.
  engine::EngineOptions engine;
  // RocksDB tuning; `path` is ignored, the database is data_dir/db.
  storage::RocksDbStoreOptions storage;
  // Workers running engine calls and the length of their queue.
  transport::WorkQueueOptions work;
  // Per-client stream limit of the gRPC service.
  transport::ServiceOptions service;
  // Embedded mode's write path (engine::WritePath): the backlog bound and
  // the appliers.
  engine::WritePathOptions write_path;
  // Consolidate and SampleReplay wait this long at most for the uploads
  // acknowledged before them to be applied (transport::EmbeddedOptions).
  absl::Duration write_path_max_apply_wait = absl::Seconds(30);
  // Largest request message accepted (gRPC answers RESOURCE_EXHAUSTED).
  size_t max_receive_message_bytes = size_t{16} << 20;
  // On SIGTERM/SIGINT, calls in flight get this long to finish.
  int shutdown_grace_seconds = 10;
  // Index snapshots while serving: every this many seconds, each changed
  // fleet with at least index_snapshot_min_codes codes in its index saves
  // one (MemoryEngine::SaveIndexSnapshots); a restart after a crash then
  // re-adds only what came after it. 0 = only at a clean shutdown. A
  // fleet's uploads wait while its snapshot is written (seconds at
  // 1,000,000 256-d traces; not while the file is synced), queries do not.
  int index_snapshot_interval_seconds = 300;
  size_t index_snapshot_min_codes = 20'000;
  // Every this many seconds the C library's free heap pages go back to the
  // system (observability::TrimHeap: memory malloc kept after calls freed
  // it, otherwise resident); 0 = never.
  int heap_trim_interval_seconds = 60;
  // Every this many seconds the fleets served here whose settings bound
  // their traces' age or number per robot get a retention call through
  // their logs (transport::EnforceRetention); 0 = never.
  int retention_interval_seconds = 60;
  SecurityConfig security;
  // HOST:PORT of the HTTP port (REST/JSON, /metrics, /healthz, /readyz,
  // dashboard); empty = off. Same auth and TLS as gRPC.
  std::string http_listen;
  // Largest HTTP request body; larger ones get 413.
  size_t max_http_body_bytes = size_t{4} << 20;
  // HTTP connections in all and per client IP address, and how long a
  // request's head may take (http::ConnectionLimits).
  size_t http_max_connections = 256;
  size_t http_max_connections_per_client = 64;
  uint32_t http_head_timeout_seconds = 10;
  // Origins (scheme://host[:port]) besides the server's own whose pages may
  // POST to the REST API (e.g. a dashboard served elsewhere).
  std::vector<std::string> http_allowed_origins;
  // Where CreateSnapshot writes (SNAPSHOT_DIR/NAME/db); empty =
  // DATA_DIR/snapshots.
  std::string snapshot_dir;
  // The readiness signal for programs that start the server (tests, the
  // demo, supervisors): once every port is bound and the service answers,
  // the server writes this file (a temporary file renamed into place, so a
  // reader never sees half of it) with one "key=value" line each:
  //   grpc=HOST:PORT   the bound gRPC address (the port a --listen of 0
  //                    picked)
  //   http=HOST:PORT   the bound HTTP address (only with http_listen)
  //   pid=PID          the server's process id
  // A file left by an earlier run is removed at start, and the file is
  // removed again when shutdown begins. Empty = none. Flag only
  // (--ready-file), not in the config file: it belongs to whoever starts
  // this process.
  std::string ready_file;
  // A snapshot directory (SNAPSHOT_DIR/NAME) to copy into the data dir
  // before starting; the data dir must hold no store yet. Flag only
  // (--restore-from): a restore is a one-time act of whoever starts the
  // server, not a setting.
  std::string restore_from;
  ClusterConfig cluster;
};

// True for 127.0.0.0/8, ::1 and "localhost" (the host part of HOST:PORT).
bool IsLoopbackListen(std::string_view listen);

// What the command line asked for; unset fields leave the file's or the
// default value.
struct CommandLine {
  bool help = false;
  bool version = false;
  std::optional<std::string> config_file;
  std::optional<std::string> listen;
  std::optional<std::string> data_dir;
  std::optional<std::string> log_level;
  std::optional<std::string> index;
  std::optional<std::string> auth_file;
  std::optional<std::string> tls_cert;
  std::optional<std::string> tls_key;
  std::optional<std::string> tls_client_ca;
  std::optional<std::string> http_listen;
  std::optional<std::string> snapshot_dir;
  std::optional<std::string> cluster;  // comma-separated NATS URLs
  std::optional<std::string> advertise;
  std::optional<std::string> ready_file;
  std::optional<std::string> restore_from;
  bool allow_unauthenticated = false;
};

// Parses argv[1..argc): --listen, --data-dir, --config, --log-level,
// --index, --auth-file, --tls-cert, --tls-key, --tls-client-ca,
// --http-listen, --snapshot-dir, --cluster, --advertise, --ready-file,
// --restore-from as
// "--name=value" or "--name value"; --allow-unauthenticated; --help or -h;
// --version.
// INVALID_ARGUMENT for an unknown flag, a missing value or a positional
// argument.
absl::StatusOr<CommandLine> ParseCommandLine(int argc, const char* const* argv);

// The --help text.
std::string Usage();

// Applies the text of a config file over `config`. INVALID_ARGUMENT naming
// line and column for a syntax error or an unknown field, and naming the
// field for a bad value (e.g. an unknown index or log level).
absl::Status ApplyConfigText(std::string_view text, ServerConfig* config);

// Applies the flags of `command_line` (not --config) over `config`;
// INVALID_ARGUMENT for an unknown log level or index.
absl::Status ApplyCommandLine(const CommandLine& command_line,
                              ServerConfig* config);

// OK if the server can start with `config`: data_dir set, listen is
// HOST:PORT, limits positive, engine options valid (ValidateEngineOptions),
// TLS files paired, and auth on or the address loopback (or
// allow_unauthenticated). Otherwise INVALID_ARGUMENT naming the setting.
absl::Status ValidateServerConfig(const ServerConfig& config);

// Defaults, then the --config file (NOT_FOUND / INVALID_ARGUMENT if it
// cannot be read or parsed), then the flags; validated.
absl::StatusOr<ServerConfig> LoadServerConfig(const CommandLine& command_line);

// Where int8 graphs keep their floats' files (graph_floats_in_files):
// data_dir/graph-floats. LoadServerConfig sets tiered.hnsw.floats_dir to it;
// the server makes it at startup and removes what a crash left there.
std::string GraphFloatsDir(const std::string& data_dir);

// One line of "name=value" pairs for the start-up log.
std::string DescribeConfig(const ServerConfig& config);

}  // namespace fleetmem::server

#endif  // FLEETMEM_SERVICES_SERVER_SERVER_CONFIG_H_
