#include "services/server/server_config.h"

#include <algorithm>
#include <climits>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <limits>
#include <sstream>
#include <utility>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "services/common/files.h"
#include "services/common/text_format.h"
#include "services/common/usage.h"
#include "services/server/server_config.pb.h"

namespace fleetmem::server {
namespace {

// Collects the text-format parser's complaints as "line L, column C: msg".
absl::Status ApplyLogLevel(std::string_view what, std::string_view text,
                           ServerConfig* config) {
  if (!log::ParseLevel(text, &config->log_level)) {
    return absl::InvalidArgumentError(absl::StrCat(
        std::string(what), ": unknown log level \"", std::string(text),
        "\" (want debug, info, warning or error)"));
  }
  return absl::OkStatus();
}

absl::Status ApplyIndex(std::string_view what, std::string_view text,
                        ServerConfig* config) {
  if (!ParseIndexKind(text, &config->index)) {
    return absl::InvalidArgumentError(
        absl::StrCat(std::string(what), ": unknown index \"", std::string(text),
                     "\" (want auto, exact, hnsw or flann)"));
  }
  return absl::OkStatus();
}

void ApplyMemory(const MemoryConfig& in, core::MemoryOptions* out) {
  if (in.has_clusters_per_batch()) {
    out->clusters_per_batch = in.clusters_per_batch();
  }
  if (in.has_max_traces_per_cluster()) {
    out->max_traces_per_cluster = in.max_traces_per_cluster();
  }
  if (in.has_max_clusters()) out->max_clusters = in.max_clusters();
  if (in.has_replay_decay()) out->replay_decay = in.replay_decay();
  if (in.has_reward_floor()) out->reward_floor = in.reward_floor();
  if (in.has_spatial_scale_m()) out->spatial_scale_m = in.spatial_scale_m();
  if (in.has_clustering()) out->clustering = in.clustering();
  if (in.has_kmeans_max_iterations()) {
    out->kmeans_max_iterations = in.kmeans_max_iterations();
  }
  if (in.has_seed()) out->seed = in.seed();
  if (in.has_forgetting_exact_below()) {
    out->forgetting_exact_below = in.forgetting_exact_below();
  }
  if (in.has_merge_on_forget()) out->merge_on_forget = in.merge_on_forget();
  if (in.has_refresh_pair_radius()) {
    out->refresh_pair_radius = in.refresh_pair_radius();
  }
  if (in.has_refresh_uniform()) out->refresh_uniform = in.refresh_uniform();
}

void ApplyEngine(const EngineConfig& in, engine::EngineOptions* out) {
  if (in.has_segment_size()) out->segment_size = in.segment_size();
  if (in.has_max_traces_per_upload()) {
    out->max_traces_per_upload = in.max_traces_per_upload();
  }
  if (in.has_max_sample_count()) {
    out->max_sample_count = in.max_sample_count();
  }
  if (in.has_max_query_k()) out->max_query_k = in.max_query_k();
  if (in.has_max_events_per_read()) {
    out->max_events_per_read = in.max_events_per_read();
  }
  if (in.has_max_events_per_fleet()) {
    out->max_events_per_fleet = in.max_events_per_fleet();
  }
  if (in.has_max_read_bytes()) out->max_read_bytes = in.max_read_bytes();
}

void ApplyLimits(const LimitsConfig& in, engine::QuotaOptions* out,
                 transport::ServiceOptions* service) {
  if (in.has_fleet_traces_per_second()) {
    out->fleet_traces_per_second = in.fleet_traces_per_second();
  }
  if (in.has_fleet_bytes_per_second()) {
    out->fleet_bytes_per_second = in.fleet_bytes_per_second();
  }
  if (in.has_robot_traces_per_second()) {
    out->robot_traces_per_second = in.robot_traces_per_second();
  }
  if (in.has_robot_bytes_per_second()) {
    out->robot_bytes_per_second = in.robot_bytes_per_second();
  }
  if (in.has_burst_seconds()) out->burst_seconds = in.burst_seconds();
  if (in.has_max_traces_per_fleet()) {
    out->max_traces_per_fleet = in.max_traces_per_fleet();
  }
  if (in.has_max_fleets()) out->max_fleets = in.max_fleets();
  if (in.has_max_code_dimension()) {
    out->max_code_dimension = in.max_code_dimension();
  }
  if (in.has_auto_create_fleets()) {
    out->auto_create_fleets = in.auto_create_fleets();
  }
  if (in.has_stream_idle_seconds()) {
    service->stream_idle_timeout = absl::Seconds(in.stream_idle_seconds());
  }
  if (in.has_max_streams_per_client()) {
    service->max_streams_per_client = in.max_streams_per_client();
  }
}

void ApplyStorage(const StorageConfig& in, storage::RocksDbStoreOptions* out) {
  if (in.has_sync()) out->sync = in.sync();
  if (in.has_block_cache_bytes()) {
    out->block_cache_bytes = in.block_cache_bytes();
  }
  if (in.has_write_buffer_bytes()) {
    out->write_buffer_bytes = in.write_buffer_bytes();
  }
  if (in.has_bloom_bits_per_key()) {
    out->bloom_bits_per_key = in.bloom_bits_per_key();
  }
  if (in.has_background_jobs()) out->background_jobs = in.background_jobs();
  if (in.has_compress()) out->compress = in.compress();
  if (in.has_min_free_bytes()) out->min_free_bytes = in.min_free_bytes();
}

void ApplyWritePath(const WritePathConfig& in, ServerConfig* out) {
  if (in.has_max_backlog_traces()) {
    out->write_path.max_backlog_traces = in.max_backlog_traces();
  }
  if (in.has_appliers()) {
    out->write_path.appliers = static_cast<int>(
        std::min<uint32_t>(in.appliers(), std::numeric_limits<int>::max()));
  }
  if (in.has_max_apply_wait_seconds()) {
    out->write_path_max_apply_wait = absl::Seconds(in.max_apply_wait_seconds());
  }
  if (in.has_background_nice()) {
    const int nice = static_cast<int>(
        std::min<uint32_t>(in.background_nice(), 1000));  // validated below
    out->write_path.applier_nice = nice;
    out->tiered.indexer_nice = nice;
  }
}

void ApplyHnsw(const HnswConfig& in, index::TieredIndexOptions* out) {
  if (in.has_m()) out->hnsw.m = in.m();
  if (in.has_ef_construction())
    out->hnsw.ef_construction = in.ef_construction();
  if (in.has_ef_search()) out->hnsw.ef_search = in.ef_search();
  if (in.has_hnsw_from()) out->hnsw_from = in.hnsw_from();
  if (in.has_max_unindexed()) out->max_unindexed = in.max_unindexed();
  if (in.has_insert_threads()) out->hnsw.insert_threads = in.insert_threads();
  if (in.has_rescore_oversample()) {
    out->hnsw.rescore_oversample = in.rescore_oversample();
  }
  if (in.has_indexer_batch()) out->indexer_batch = in.indexer_batch();
}

void ApplyFlann(const FlannConfig& in, index::FlannIndexOptions* out) {
  if (in.has_trees()) out->trees = in.trees();
  if (in.has_checks()) out->checks = in.checks();
  if (in.has_rebuild_removed_fraction()) {
    out->rebuild_removed_fraction = in.rebuild_removed_fraction();
  }
  if (in.has_add_rebuild_factor()) {
    out->add_rebuild_factor = in.add_rebuild_factor();
  }
  if (in.has_accept_oversample()) {
    out->accept_oversample = in.accept_oversample();
  }
}

void ApplyCluster(const ClusterConfigFile& in, ClusterConfig* out) {
  if (in.servers_size() > 0) {
    out->nats.servers.assign(in.servers().begin(), in.servers().end());
  }
  if (in.has_advertise()) out->advertise = in.advertise();
  if (in.has_replicas()) out->nats.replicas = in.replicas();
  if (in.has_lease_ttl_ms()) {
    out->nats.lease_ttl = absl::Milliseconds(in.lease_ttl_ms());
  }
  if (in.has_round_interval_ms()) {
    out->round_interval = absl::Milliseconds(in.round_interval_ms());
  }
  if (in.has_max_entry_bytes()) out->max_entry_bytes = in.max_entry_bytes();
  if (in.has_nats_credentials_file()) {
    out->nats.credentials_file = in.nats_credentials_file();
  }
  if (in.has_nats_ca_file()) out->nats.ca_file = in.nats_ca_file();
  if (in.has_nats_cert_file()) out->nats.cert_file = in.nats_cert_file();
  if (in.has_nats_key_file()) out->nats.key_file = in.nats_key_file();
  if (in.has_peer_token_file()) out->peer_token_file = in.peer_token_file();
  if (in.has_peer_ca_file()) out->peer_ca_file = in.peer_ca_file();
  if (in.has_sync_store()) out->sync_store = in.sync_store();
  if (in.has_snapshot_every_entries()) {
    out->snapshot_every_entries = in.snapshot_every_entries();
  }
  if (in.has_trim_log()) out->trim_log = in.trim_log();
  if (in.has_balance_fleets()) out->balance_fleets = in.balance_fleets();
  if (in.has_peer_tls_server_name()) {
    out->peer_tls_server_name = in.peer_tls_server_name();
  }
  if (in.has_connect_timeout_seconds()) {
    out->connect_timeout = absl::Seconds(in.connect_timeout_seconds());
  }
}

void ApplySecurity(const SecurityConfigFile& in, SecurityConfig* out) {
  if (in.has_auth_file()) out->auth_file = in.auth_file();
  if (in.has_allow_unauthenticated()) {
    out->allow_unauthenticated = in.allow_unauthenticated();
  }
  if (in.has_tls_cert_file()) out->tls_cert_file = in.tls_cert_file();
  if (in.has_tls_key_file()) out->tls_key_file = in.tls_key_file();
  if (in.has_tls_client_ca_file()) {
    out->tls_client_ca_file = in.tls_client_ca_file();
  }
  if (in.has_require_client_certificate()) {
    out->require_client_certificate = in.require_client_certificate();
  }
  if (in.has_tls_reload_seconds()) {
    out->tls_reload_seconds =
        static_cast<int>(std::min<uint32_t>(in.tls_reload_seconds(), 86400));
  }
  if (in.has_metrics_without_auth()) {
    out->metrics_without_auth = in.metrics_without_auth();
  }
  if (in.has_reflection_with_auth()) {
    out->reflection_with_auth = in.reflection_with_auth();
  }
}

// The flags that take a value, and where they go.
struct FlagSpec {
  std::string_view name;
  std::optional<std::string> CommandLine::*field;
  std::string_view value_name;
  std::string_view help;
};

const FlagSpec kFlags[] = {
    {"listen", &CommandLine::listen, "HOST:PORT",
     "address to listen on; port 0 picks a free port (default "
     "127.0.0.1:50051)"},
    {"data-dir", &CommandLine::data_dir, "DIR",
     "folder of the server's state, created if missing; RocksDB lives in "
     "DIR/db (required, here or in the config file)"},
    {"config", &CommandLine::config_file, "FILE",
     "config file in protobuf text format (services/server/"
     "server_config.proto); flags override it"},
    {"log-level", &CommandLine::log_level, "LEVEL",
     "debug, info, warning or error (default info)"},
    {"index", &CommandLine::index, "KIND",
     "place index: auto, exact, hnsw or flann (default auto)"},
    {"auth-file", &CommandLine::auth_file, "FILE",
     "credentials file (services/auth/credentials.proto): turns auth on; "
     "re-read on SIGHUP"},
    {"tls-cert", &CommandLine::tls_cert, "FILE",
     "PEM certificate chain of the server: TLS on (with --tls-key)"},
    {"tls-key", &CommandLine::tls_key, "FILE", "PEM private key of --tls-cert"},
    {"tls-client-ca", &CommandLine::tls_client_ca, "FILE",
     "PEM CA bundle for client certificates (mutual TLS)"},
    {"http-listen", &CommandLine::http_listen, "HOST:PORT",
     "HTTP port: REST/JSON under /v1/, /metrics, /healthz, /readyz and the "
     "dashboard at /; same auth and TLS as gRPC (default off)"},
    {"snapshot-dir", &CommandLine::snapshot_dir, "DIR",
     "where CreateSnapshot writes DIR/NAME (default DATA_DIR/snapshots)"},
    {"cluster", &CommandLine::cluster, "URL,...",
     "distributed mode on NATS JetStream (nats://HOST:PORT,...; "
     "docs/distributed.md); needs --advertise"},
    {"advertise", &CommandLine::advertise, "HOST:PORT",
     "where the other replicas reach this one (its replica id)"},
    {"ready-file", &CommandLine::ready_file, "FILE",
     "written once the server serves: grpc=HOST:PORT, http=HOST:PORT (with "
     "--http-listen) and pid=PID, one per line; removed at shutdown (the "
     "readiness signal for whoever starts the server)"},
    {"restore-from", &CommandLine::restore_from, "DIR",
     "a snapshot (SNAPSHOT_DIR/NAME, from `fleetmem snapshot`) copied into "
     "--data-dir, which must hold no store yet, before the server starts; "
     "the snapshot is left as it was (a server refuses to run on a snapshot "
     "itself)"},
};

constexpr std::string_view kAllowUnauthenticated = "allow-unauthenticated";

// "host:port" -> port, or nullopt if malformed.
std::optional<int> ListenPort(std::string_view listen) {
  size_t colon = listen.rfind(':');
  if (colon == std::string_view::npos || colon == 0) return std::nullopt;
  int port = 0;
  if (!absl::SimpleAtoi(std::string(listen.substr(colon + 1)), &port))
    return std::nullopt;
  if (port < 0 || port > 65535) return std::nullopt;
  return port;
}

absl::Status ValidateCluster(const ServerConfig& config) {
  const ClusterConfig& cluster = config.cluster;
  if (!cluster.enabled()) return absl::OkStatus();
  // Its messages begin with "cluster: ".
  absl::Status status = cluster::ValidateNatsOptions(cluster.nats);
  if (!status.ok()) return status;
  const std::optional<int> port = ListenPort(cluster.advertise);
  if (!port.has_value() || *port == 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cluster.advertise: \"", cluster.advertise,
        "\" is not HOST:PORT with a fixed port (the other replicas forward "
        "calls there; give --advertise)"));
  }
  if (cluster.nats.lease_ttl < absl::Seconds(1) ||
      cluster.round_interval <= absl::ZeroDuration() ||
      cluster.round_interval * 3 > cluster.nats.lease_ttl) {
    return absl::InvalidArgumentError(
        "cluster: lease_ttl_ms must be at least 1000 and at least three "
        "round_interval_ms (a lease is renewed every third of it)");
  }
  if (cluster.max_entry_bytes < 4096) {
    return absl::InvalidArgumentError("cluster.max_entry_bytes: at least 4096");
  }
  if (!config.security.auth_file.empty() && cluster.peer_token_file.empty()) {
    return absl::InvalidArgumentError(
        "cluster.peer_token_file: required with auth on (the token of an "
        "admin principal replicas forward calls with)");
  }
  return absl::OkStatus();
}

}  // namespace

bool ParseIndexKind(std::string_view text, IndexKind* kind) {
  if (text == "auto") {
    *kind = IndexKind::kAuto;
  } else if (text == "exact") {
    *kind = IndexKind::kExact;
  } else if (text == "hnsw") {
    *kind = IndexKind::kHnsw;
  } else if (text == "flann") {
    *kind = IndexKind::kFlann;
  } else {
    return false;
  }
  return true;
}

std::string_view IndexKindName(IndexKind kind) {
  switch (kind) {
    case IndexKind::kAuto:
      return "auto";
    case IndexKind::kExact:
      return "exact";
    case IndexKind::kHnsw:
      return "hnsw";
    case IndexKind::kFlann:
      return "flann";
  }
  return "?";
}

absl::StatusOr<CommandLine> ParseCommandLine(int argc,
                                             const char* const* argv) {
  CommandLine out;
  for (int i = 1; i < argc; ++i) {
    std::string_view arg = argv[i];
    if (arg == "--help" || arg == "-help" || arg == "-h") {
      out.help = true;
      continue;
    }
    if (arg == "--version") {
      out.version = true;
      continue;
    }
    if (arg.substr(0, 2) != "--" || arg.size() == 2) {
      return absl::InvalidArgumentError(
          absl::StrCat("unexpected argument \"", std::string(arg), "\""));
    }
    arg.remove_prefix(2);
    if (arg == kAllowUnauthenticated) {
      out.allow_unauthenticated = true;
      continue;
    }
    std::string_view name = arg;
    std::optional<std::string_view> value;
    if (size_t eq = arg.find('='); eq != std::string_view::npos) {
      name = arg.substr(0, eq);
      value = arg.substr(eq + 1);
    }
    const FlagSpec* spec = nullptr;
    for (const FlagSpec& candidate : kFlags) {
      if (candidate.name == name) spec = &candidate;
    }
    if (spec == nullptr) {
      return absl::InvalidArgumentError(
          absl::StrCat("unknown flag --", std::string(name)));
    }
    if (!value.has_value()) {
      if (i + 1 >= argc) {
        return absl::InvalidArgumentError(
            absl::StrCat("flag --", std::string(name), " needs a value (",
                         std::string(spec->value_name), ")"));
      }
      value = argv[++i];
    }
    out.*(spec->field) = std::string(*value);
  }
  return out;
}

std::string Usage() {
  common::UsageText text;
  text.description =
      "fleetmem-server: serves fleetmem.v1.MemoryService (gRPC; REST/JSON and "
      "the dashboard with --http-listen) until SIGTERM or SIGINT.";
  text.usage = {"fleetmem-server --data-dir DIR [OPTIONS]"};
  common::UsageSection options{"Options", {}};
  for (const FlagSpec& flag : kFlags) {
    options.items.push_back(
        {"--" + std::string(flag.name) + " " + std::string(flag.value_name),
         std::string(flag.help)});
  }
  options.items.push_back(
      {"--" + std::string(kAllowUnauthenticated),
       "serve without --auth-file on a non-loopback address (anyone who "
       "reaches the port may do anything)"});
  options.items.push_back({"-h, --help", "print this help and exit"});
  options.items.push_back({"--version", "print the version and exit"});
  text.sections.push_back(std::move(options));
  text.footer =
      "Exit status: 0 after a clean shutdown, --help or --version; 1 a "
      "failure while serving (the reason logged); 2 bad usage or "
      "configuration.";
  return common::FormatUsage(text);
}

// ApplyConfigText's parts: the ports and paths; the timed tasks' periods;
// the fleets' own memory bounds (over the server's).
void ApplyServing(const ServerConfigFile& file, ServerConfig* config) {
  if (file.has_listen()) config->listen = file.listen();
  if (file.has_data_dir()) config->data_dir = file.data_dir();
  if (file.has_http_listen()) config->http_listen = file.http_listen();
  if (file.has_max_http_body_bytes()) {
    config->max_http_body_bytes = file.max_http_body_bytes();
  }
  if (file.has_http_max_connections()) {
    config->http_max_connections = file.http_max_connections();
  }
  if (file.has_http_max_connections_per_client()) {
    config->http_max_connections_per_client =
        file.http_max_connections_per_client();
  }
  if (file.has_http_head_timeout_seconds()) {
    config->http_head_timeout_seconds = file.http_head_timeout_seconds();
  }
  if (file.http_allowed_origins_size() > 0) {
    config->http_allowed_origins.assign(file.http_allowed_origins().begin(),
                                        file.http_allowed_origins().end());
  }
  if (file.has_snapshot_dir()) config->snapshot_dir = file.snapshot_dir();
}

absl::Status ApplyPeriods(const ServerConfigFile& file, ServerConfig* config) {
  if (file.has_shutdown_grace_seconds()) {
    if (file.shutdown_grace_seconds() > 3600) {
      return absl::InvalidArgumentError("shutdown_grace_seconds: at most 3600");
    }
    config->shutdown_grace_seconds =
        static_cast<int>(file.shutdown_grace_seconds());
  }
  if (file.has_index_snapshot_interval_seconds()) {
    if (file.index_snapshot_interval_seconds() > 86400) {
      return absl::InvalidArgumentError(
          "index_snapshot_interval_seconds: at most 86400 (0 = only at a "
          "clean shutdown)");
    }
    config->index_snapshot_interval_seconds =
        static_cast<int>(file.index_snapshot_interval_seconds());
  }
  if (file.has_index_snapshot_min_codes()) {
    config->index_snapshot_min_codes = file.index_snapshot_min_codes();
  }
  if (file.has_retention_interval_seconds()) {
    if (file.retention_interval_seconds() > 86400) {
      return absl::InvalidArgumentError(
          "retention_interval_seconds: at most 86400 (0 = never)");
    }
    config->retention_interval_seconds =
        static_cast<int>(file.retention_interval_seconds());
  }
  if (file.has_heap_trim_interval_seconds()) {
    if (file.heap_trim_interval_seconds() > 86400) {
      return absl::InvalidArgumentError(
          "heap_trim_interval_seconds: at most 86400 (0 = never)");
    }
    config->heap_trim_interval_seconds =
        static_cast<int>(file.heap_trim_interval_seconds());
  }
  return absl::OkStatus();
}

absl::Status ApplyFleets(const ServerConfigFile& file, ServerConfig* config) {
  for (const FleetMemoryConfig& fleet : file.fleets()) {
    core::MemoryOptions memory = config->engine.memory;
    ApplyMemory(fleet.memory(), &memory);
    if (!config->engine.fleet_memory.emplace(fleet.fleet_id(), memory).second) {
      return absl::InvalidArgumentError(absl::StrCat(
          "fleets: fleet_id \"", fleet.fleet_id(), "\" is configured twice"));
    }
  }
  return absl::OkStatus();
}

absl::Status ApplyConfigText(std::string_view text, ServerConfig* config) {
  ServerConfigFile file;
  if (absl::Status syntax = ParseTextFormat(text, &file); !syntax.ok()) {
    return syntax;
  }
  ApplyServing(file, config);
  if (file.has_log_level()) {
    absl::Status status = ApplyLogLevel("log_level", file.log_level(), config);
    if (!status.ok()) return status;
  }
  if (file.has_index()) {
    absl::Status status = ApplyIndex("index", file.index(), config);
    if (!status.ok()) return status;
  }
  if (file.has_worker_threads()) config->work.threads = file.worker_threads();
  if (file.has_max_queued_calls()) {
    config->work.max_queued = file.max_queued_calls();
  }
  if (file.has_max_receive_message_bytes()) {
    config->max_receive_message_bytes = file.max_receive_message_bytes();
  }
  if (absl::Status periods = ApplyPeriods(file, config); !periods.ok()) {
    return periods;
  }
  ApplyMemory(file.memory(), &config->engine.memory);
  if (absl::Status fleets = ApplyFleets(file, config); !fleets.ok()) {
    return fleets;
  }
  ApplyEngine(file.engine(), &config->engine);
  ApplyStorage(file.storage(), &config->storage);
  ApplyFlann(file.flann(), &config->flann);
  ApplyHnsw(file.hnsw(), &config->tiered);
  if (file.hnsw().has_codes()) {
    std::optional<index::HnswIndexOptions::Codes> codes =
        index::ParseHnswCodes(file.hnsw().codes());
    if (!codes.has_value()) {
      return absl::InvalidArgumentError(
          absl::StrCat("hnsw.codes: unknown \"", file.hnsw().codes(),
                       "\" (want int8 or float)"));
    }
    config->tiered.hnsw.codes = *codes;
  }
  if (file.hnsw().has_floats()) {
    const std::string& floats = file.hnsw().floats();
    if (floats != "file" && floats != "memory") {
      return absl::InvalidArgumentError(absl::StrCat(
          "hnsw.floats: unknown \"", floats, "\" (want file or memory)"));
    }
    config->graph_floats_in_files = floats == "file";
  }
  ApplySecurity(file.security(), &config->security);
  ApplyCluster(file.cluster(), &config->cluster);
  ApplyWritePath(file.write_path(), config);
  ApplyLimits(file.limits(), &config->engine.limits, &config->service);
  return absl::OkStatus();
}

absl::Status ApplyCommandLine(const CommandLine& command_line,
                              ServerConfig* config) {
  if (command_line.listen) config->listen = *command_line.listen;
  if (command_line.data_dir) config->data_dir = *command_line.data_dir;
  if (command_line.http_listen) {
    config->http_listen = *command_line.http_listen;
  }
  if (command_line.cluster) {
    config->cluster.nats.servers =
        absl::StrSplit(*command_line.cluster, ',', absl::SkipEmpty());
  }
  if (command_line.advertise)
    config->cluster.advertise = *command_line.advertise;
  if (command_line.snapshot_dir) {
    config->snapshot_dir = *command_line.snapshot_dir;
  }
  if (command_line.ready_file) config->ready_file = *command_line.ready_file;
  if (command_line.restore_from) {
    config->restore_from = *command_line.restore_from;
  }
  if (command_line.log_level) {
    absl::Status status =
        ApplyLogLevel("--log-level", *command_line.log_level, config);
    if (!status.ok()) return status;
  }
  if (command_line.index) {
    absl::Status status = ApplyIndex("--index", *command_line.index, config);
    if (!status.ok()) return status;
  }
  SecurityConfig& security = config->security;
  if (command_line.auth_file) security.auth_file = *command_line.auth_file;
  if (command_line.tls_cert) security.tls_cert_file = *command_line.tls_cert;
  if (command_line.tls_key) security.tls_key_file = *command_line.tls_key;
  if (command_line.tls_client_ca) {
    security.tls_client_ca_file = *command_line.tls_client_ca;
  }
  if (command_line.allow_unauthenticated) security.allow_unauthenticated = true;
  return absl::OkStatus();
}

namespace {

// The server's own settings: where it stores and listens, and the sizes of
// its queues, threads and index.
absl::Status ValidateServing(const ServerConfig& config) {
  if (config.data_dir.empty()) {
    return absl::InvalidArgumentError(
        "data_dir: required (--data-dir DIR or data_dir in the config file)");
  }
  if (!ListenPort(config.listen).has_value()) {
    return absl::InvalidArgumentError(
        absl::StrCat("listen: \"", config.listen,
                     "\" is not HOST:PORT with a port in 0..65535"));
  }
  if (config.max_receive_message_bytes == 0 ||
      config.max_receive_message_bytes > static_cast<size_t>(INT_MAX)) {
    return absl::InvalidArgumentError(
        absl::StrCat("max_receive_message_bytes: must be in 1..", INT_MAX));
  }
  if (config.work.max_queued == 0) {
    return absl::InvalidArgumentError("max_queued_calls: must be positive");
  }
  if (config.tiered.hnsw.m < 2 || config.tiered.hnsw.m > 256) {
    return absl::InvalidArgumentError("hnsw.m: must be in 2..256");
  }
  if (config.tiered.hnsw.ef_construction < 1 ||
      config.tiered.hnsw.ef_search < 1) {
    return absl::InvalidArgumentError(
        "hnsw.ef_construction and hnsw.ef_search: must be positive");
  }
  if (config.tiered.hnsw_from < 2) {
    return absl::InvalidArgumentError("hnsw.hnsw_from: must be at least 2");
  }
  if (config.tiered.hnsw.insert_threads < 1 ||
      config.tiered.hnsw.insert_threads > 64) {
    return absl::InvalidArgumentError("hnsw.insert_threads: must be in 1..64");
  }
  if (config.tiered.hnsw.rescore_oversample < 1 ||
      config.tiered.hnsw.rescore_oversample > 64) {
    return absl::InvalidArgumentError(
        "hnsw.rescore_oversample: must be in 1..64");
  }
  if (config.tiered.indexer_batch > 64) {
    return absl::InvalidArgumentError(
        "hnsw.indexer_batch: must be in 0..64 (0: by the codes)");
  }
  if (config.work.threads > 1024) {
    return absl::InvalidArgumentError("worker_threads: at most 1024");
  }
  if (config.storage.background_jobs < 1) {
    return absl::InvalidArgumentError(
        "storage.background_jobs: must be positive");
  }
  if (config.storage.bloom_bits_per_key < 0) {
    return absl::InvalidArgumentError(
        "storage.bloom_bits_per_key: must not be negative");
  }
  if (config.shutdown_grace_seconds < 0) {
    return absl::InvalidArgumentError(
        "shutdown_grace_seconds: must not be negative");
  }
  if (config.index_snapshot_interval_seconds < 0) {
    return absl::InvalidArgumentError(
        "index_snapshot_interval_seconds: must not be negative");
  }
  return absl::OkStatus();
}

// Who may reach it and how: TLS, client certificates, the HTTP port, and
// no unauthenticated port beyond loopback unless asked for.
absl::Status ValidateExposure(const ServerConfig& config) {
  const SecurityConfig& security = config.security;
  if (security.tls_cert_file.empty() != security.tls_key_file.empty()) {
    return absl::InvalidArgumentError(
        "tls_cert_file / tls_key_file: give both (--tls-cert and --tls-key) "
        "or neither");
  }
  if (!security.tls_client_ca_file.empty() && security.tls_cert_file.empty()) {
    return absl::InvalidArgumentError(
        "tls_client_ca_file: client certificates need TLS (--tls-cert and "
        "--tls-key)");
  }
  if (security.require_client_certificate &&
      security.tls_client_ca_file.empty()) {
    return absl::InvalidArgumentError(
        "require_client_certificate: needs tls_client_ca_file");
  }
  if (security.tls_reload_seconds < 1) {
    return absl::InvalidArgumentError("tls_reload_seconds: must be positive");
  }
  if (!config.http_listen.empty() &&
      !ListenPort(config.http_listen).has_value()) {
    return absl::InvalidArgumentError(
        absl::StrCat("http_listen: \"", config.http_listen,
                     "\" is not HOST:PORT with a port in 0..65535"));
  }
  if (config.service.stream_idle_timeout < absl::Seconds(1)) {
    return absl::InvalidArgumentError(
        "limits.stream_idle_seconds: must be at least 1");
  }
  if (config.max_http_body_bytes < 1024) {
    return absl::InvalidArgumentError(
        "max_http_body_bytes: must be at least 1024");
  }
  if (config.http_max_connections == 0 ||
      config.http_max_connections_per_client == 0 ||
      config.http_head_timeout_seconds == 0) {
    return absl::InvalidArgumentError(
        "http_max_connections, http_max_connections_per_client and "
        "http_head_timeout_seconds must be at least 1");
  }
  if (security.auth_file.empty() && !security.allow_unauthenticated &&
      !config.http_listen.empty() && !IsLoopbackListen(config.http_listen)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "http_listen: refusing to serve ", config.http_listen,
        " without authentication; give --auth-file FILE, or "
        "--allow-unauthenticated if anyone who reaches the port may read "
        "and write every fleet"));
  }
  if (security.auth_file.empty() && !security.allow_unauthenticated &&
      !IsLoopbackListen(config.listen)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "listen: refusing to serve ", config.listen,
        " without authentication; give --auth-file FILE, or "
        "--allow-unauthenticated if anyone who reaches the port may read "
        "and write every fleet"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status ValidateServerConfig(const ServerConfig& config) {
  if (absl::Status serving = ValidateServing(config); !serving.ok()) {
    return serving;
  }
  if (absl::Status exposure = ValidateExposure(config); !exposure.ok()) {
    return exposure;
  }
  if (absl::Status write_path =
          engine::ValidateWritePathOptions(config.write_path);
      !write_path.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("write_path: ", write_path.message()));
  }
  if (config.write_path_max_apply_wait <= absl::ZeroDuration()) {
    return absl::InvalidArgumentError(
        "write_path.max_apply_wait_seconds must be at least 1");
  }
  absl::Status cluster = ValidateCluster(config);
  if (!cluster.ok()) return cluster;
  return engine::ValidateEngineOptions(config.engine);
}

bool IsLoopbackListen(std::string_view listen) {
  const size_t colon = listen.rfind(':');
  std::string_view host =
      colon == std::string_view::npos ? listen : listen.substr(0, colon);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  if (host == "localhost" || host == "::1") return true;
  return host.substr(0, 4) == "127.";
}

absl::StatusOr<ServerConfig> LoadServerConfig(const CommandLine& command_line) {
  ServerConfig config;
  if (command_line.config_file) {
    const std::string& path = *command_line.config_file;
    absl::StatusOr<std::string> text = files::ReadFile(path);
    if (!text.ok()) {
      return absl::Status(
          text.status().code(),
          absl::StrCat("config file ", path, ": cannot be read"));
    }
    absl::Status status = ApplyConfigText(*text, &config);
    if (!status.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("config file ", path, ": ", status.message()));
    }
  }
  absl::Status status = ApplyCommandLine(command_line, &config);
  if (!status.ok()) return status;
  status = ValidateServerConfig(config);
  if (!status.ok()) return status;
  if (config.graph_floats_in_files) {
    config.tiered.hnsw.floats_dir = GraphFloatsDir(config.data_dir);
  }
  return config;
}

std::string GraphFloatsDir(const std::string& data_dir) {
  return (std::filesystem::path(data_dir) / "graph-floats").string();
}

std::string DescribeConfig(const ServerConfig& config) {
  const core::MemoryOptions& memory = config.engine.memory;
  std::string out = absl::StrCat(
      "index=", std::string(IndexKindName(config.index)),
      " worker_threads=", transport::WorkerThreads(config.work),
      " max_queued_calls=", config.work.max_queued,
      " max_receive_message_bytes=", config.max_receive_message_bytes,
      " clusters_per_batch=", memory.clusters_per_batch,
      " max_traces_per_cluster=", memory.max_traces_per_cluster,
      " max_clusters=", memory.max_clusters,
      " replay_decay=", memory.replay_decay,
      " reward_floor=", memory.reward_floor,
      " spatial_scale_m=", memory.spatial_scale_m,
      " clustering=", memory.clustering ? "true" : "false",
      " merge_on_forget=", memory.merge_on_forget ? "true" : "false",
      " refresh_pair_radius=", memory.refresh_pair_radius,
      " refresh_uniform=", memory.refresh_uniform ? "true" : "false",
      " kmeans_max_iterations=", memory.kmeans_max_iterations,
      " seed=", memory.seed, " segment_size=", config.engine.segment_size,
      " max_traces_per_upload=", config.engine.max_traces_per_upload,
      " max_sample_count=", config.engine.max_sample_count,
      " max_query_k=", config.engine.max_query_k,
      " max_read_bytes=", config.engine.max_read_bytes,
      " max_events_per_read=", config.engine.max_events_per_read,
      " max_events_per_fleet=", config.engine.max_events_per_fleet,
      " max_fleets=", config.engine.limits.max_fleets, " auto_create_fleets=",
      config.engine.limits.auto_create_fleets ? "true" : "false",
      " max_traces_per_fleet=", config.engine.limits.max_traces_per_fleet,
      " max_code_dimension=", config.engine.limits.max_code_dimension,
      " robot_traces_per_second=", config.engine.limits.robot_traces_per_second,
      " fleet_traces_per_second=", config.engine.limits.fleet_traces_per_second,
      " max_streams_per_client=", config.service.max_streams_per_client,
      " rocksdb_sync=", config.storage.sync ? "true" : "false",
      " min_free_bytes=", config.storage.min_free_bytes,
      " shutdown_grace_seconds=", config.shutdown_grace_seconds,
      " index_snapshot_interval_seconds=",
      config.index_snapshot_interval_seconds,
      " index_snapshot_min_codes=", config.index_snapshot_min_codes,
      " heap_trim_interval_seconds=", config.heap_trim_interval_seconds,
      " retention_interval_seconds=", config.retention_interval_seconds,
      " max_backlog_traces=", config.write_path.max_backlog_traces,
      " appliers=", config.write_path.appliers,
      " background_nice=", config.write_path.applier_nice,
      " auth=", config.security.auth_file.empty() ? "off" : "on",
      " tls=", config.security.tls_cert_file.empty() ? "off" : "on",
      " client_certificates=",
      config.security.tls_client_ca_file.empty()
          ? "off"
          : (config.security.require_client_certificate ? "required"
                                                        : "optional"));
  if (config.index == IndexKind::kAuto || config.index == IndexKind::kHnsw) {
    absl::StrAppend(
        &out, " hnsw_m=", config.tiered.hnsw.m,
        " hnsw_ef_search=", config.tiered.hnsw.ef_search,
        " hnsw_insert_threads=", config.tiered.hnsw.insert_threads,
        " hnsw_codes=",
        std::string(index::HnswCodesName(config.tiered.hnsw.codes)),
        " hnsw_floats=", config.graph_floats_in_files ? "file" : "memory");
    if (config.index == IndexKind::kAuto) {
      absl::StrAppend(&out, " hnsw_from=", config.tiered.hnsw_from,
                      " max_unindexed=", config.tiered.max_unindexed);
    }
  }
  if (config.index == IndexKind::kFlann) {
    absl::StrAppend(&out, " flann_trees=", config.flann.trees,
                    " flann_checks=", config.flann.checks);
  }
  return out;
}

}  // namespace fleetmem::server
