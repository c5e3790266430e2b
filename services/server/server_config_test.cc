#include "services/server/server_config.h"

#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::server {
namespace {

absl::StatusOr<CommandLine> Parse(std::vector<std::string> args) {
  std::vector<const char*> argv = {"fleetmem-server"};
  for (const std::string& arg : args) argv.push_back(arg.c_str());
  return ParseCommandLine(static_cast<int>(argv.size()), argv.data());
}

TEST(ParseCommandLineTest, BothFlagForms) {
  absl::StatusOr<CommandLine> parsed =
      Parse({"--listen=0.0.0.0:0", "--data-dir", "/tmp/x", "--log-level",
             "debug", "--index=flann", "--config", "a.textproto"});
  ASSERT_TRUE(parsed.ok()) << parsed.status();
  EXPECT_FALSE(parsed->help);
  EXPECT_EQ(parsed->listen, "0.0.0.0:0");
  EXPECT_EQ(parsed->data_dir, "/tmp/x");
  EXPECT_EQ(parsed->log_level, "debug");
  EXPECT_EQ(parsed->index, "flann");
  EXPECT_EQ(parsed->config_file, "a.textproto");
}

TEST(ParseCommandLineTest, Help) {
  for (const char* flag : {"--help", "-h"}) {
    absl::StatusOr<CommandLine> parsed = Parse({flag});
    ASSERT_TRUE(parsed.ok());
    EXPECT_TRUE(parsed->help);
  }
  EXPECT_NE(Usage().find("--data-dir"), std::string::npos);
}

TEST(ParseCommandLineTest, Errors) {
  const std::vector<std::vector<std::string>> cases = {
      {"--bogus=1"}, {"--listen"}, {"positional"}, {"--"}, {"-x"},
  };
  for (const auto& args : cases) {
    absl::StatusOr<CommandLine> parsed = Parse(args);
    EXPECT_EQ(parsed.status().code(), absl::StatusCode::kInvalidArgument)
        << args[0];
  }
}

TEST(ServerConfigTest, FileThenFlags) {
  ServerConfig config;
  ASSERT_TRUE(ApplyConfigText(R"pb(
                                listen: "10.0.0.1:7000"
                                data_dir: "/data/a"
                                log_level: "warning"
                                index: "flann"
                                worker_threads: 3
                                max_queued_calls: 7
                                max_receive_message_bytes: 1048576
                                memory {
                                  max_clusters: 200
                                  replay_decay: 1.0
                                  clustering: false
                                  seed: 7
                                }
                                engine { segment_size: 50 max_query_k: 10 }
                                storage { sync: false }
                                flann { trees: 8 checks: 64 }
                              )pb",
                              &config)
                  .ok());
  EXPECT_EQ(config.listen, "10.0.0.1:7000");
  EXPECT_EQ(config.log_level, log::Level::kWarning);
  EXPECT_EQ(config.index, IndexKind::kFlann);
  EXPECT_EQ(config.work.threads, 3u);
  EXPECT_EQ(config.work.max_queued, 7u);
  EXPECT_EQ(config.max_receive_message_bytes, 1048576u);
  EXPECT_EQ(config.engine.memory.max_clusters, 200);
  EXPECT_EQ(config.engine.memory.replay_decay, 1.0);
  EXPECT_FALSE(config.engine.memory.clustering);
  EXPECT_EQ(config.engine.memory.seed, 7u);
  // Unset fields keep their defaults.
  EXPECT_EQ(config.engine.memory.clusters_per_batch, 20);
  EXPECT_EQ(config.engine.segment_size, 50u);
  EXPECT_EQ(config.engine.max_query_k, 10u);
  EXPECT_EQ(config.engine.max_sample_count, 10000u);
  EXPECT_FALSE(config.storage.sync);
  EXPECT_EQ(config.flann.trees, 8);
  EXPECT_EQ(config.flann.checks, 64);

  CommandLine flags;
  flags.listen = "127.0.0.1:0";
  flags.index = "exact";
  ASSERT_TRUE(ApplyCommandLine(flags, &config).ok());
  EXPECT_EQ(config.listen, "127.0.0.1:0");
  EXPECT_EQ(config.index, IndexKind::kExact);
  EXPECT_EQ(config.data_dir, "/data/a");  // from the file
  EXPECT_TRUE(ValidateServerConfig(config).ok());
}

TEST(ServerConfigTest, PerFleetMemoryStartsFromTheServerWide) {
  ServerConfig config;
  config.data_dir = "/tmp/d";
  ASSERT_TRUE(ApplyConfigText(R"pb(
                                memory { max_clusters: 200 }
                                fleets {
                                  fleet_id: "ablation"
                                  memory { clustering: false replay_decay: 1 }
                                }
                              )pb",
                              &config)
                  .ok());
  ASSERT_EQ(config.engine.fleet_memory.count("ablation"), 1u);
  const core::MemoryOptions& ablation = config.engine.fleet_memory["ablation"];
  EXPECT_FALSE(ablation.clustering);
  EXPECT_EQ(ablation.replay_decay, 1.0);
  EXPECT_EQ(ablation.max_clusters, 200);  // inherited
  EXPECT_TRUE(config.engine.memory.clustering);
  EXPECT_TRUE(ValidateServerConfig(config).ok());

  ServerConfig twice;
  EXPECT_EQ(ApplyConfigText(R"pb(
                              fleets { fleet_id: "a" }
                              fleets { fleet_id: "a" }
                            )pb",
                            &twice)
                .code(),
            absl::StatusCode::kInvalidArgument);
  ServerConfig bad;
  bad.data_dir = "/tmp/d";
  ASSERT_TRUE(ApplyConfigText(R"pb(fleets {
                                     fleet_id: "a"
                                     memory { replay_decay: 2 }
                                   })pb",
                              &bad)
                  .ok());
  absl::Status status = ValidateServerConfig(bad);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("fleet \"a\""), std::string::npos) << status;
}

// The example shipped for users parses, validates and says the truth about
// the defaults it lists.
TEST(ServerConfigTest, ExampleConfigIsValid) {
  std::ifstream file(FLEETMEM_SOURCE_DIR
                     "/services/server/fleetmem-server.example.textproto");
  ASSERT_TRUE(file.good());
  std::stringstream text;
  text << file.rdbuf();
  ServerConfig config;
  ASSERT_TRUE(ApplyConfigText(text.str(), &config).ok());
  EXPECT_TRUE(ValidateServerConfig(config).ok());
  const ServerConfig defaults;
  const core::MemoryOptions& memory = config.engine.memory;
  const core::MemoryOptions& default_memory = defaults.engine.memory;
  EXPECT_EQ(memory.clusters_per_batch, default_memory.clusters_per_batch);
  EXPECT_EQ(memory.max_traces_per_cluster,
            default_memory.max_traces_per_cluster);
  EXPECT_EQ(memory.max_clusters, default_memory.max_clusters);
  EXPECT_EQ(memory.replay_decay, default_memory.replay_decay);
  EXPECT_EQ(memory.reward_floor, default_memory.reward_floor);
  EXPECT_EQ(memory.spatial_scale_m, default_memory.spatial_scale_m);
  EXPECT_EQ(memory.seed, default_memory.seed);
  EXPECT_EQ(config.engine.segment_size, defaults.engine.segment_size);
  EXPECT_EQ(config.engine.max_traces_per_upload,
            defaults.engine.max_traces_per_upload);
  EXPECT_EQ(config.engine.max_sample_count, defaults.engine.max_sample_count);
  EXPECT_EQ(config.storage.sync, defaults.storage.sync);
  EXPECT_EQ(config.storage.min_free_bytes, defaults.storage.min_free_bytes);
  EXPECT_EQ(config.http_max_connections, defaults.http_max_connections);
  EXPECT_EQ(config.http_max_connections_per_client,
            defaults.http_max_connections_per_client);
  EXPECT_EQ(config.http_head_timeout_seconds,
            defaults.http_head_timeout_seconds);
  EXPECT_EQ(config.service.stream_idle_timeout,
            defaults.service.stream_idle_timeout);
  EXPECT_EQ(config.engine.max_read_bytes, defaults.engine.max_read_bytes);
  EXPECT_EQ(config.engine.max_events_per_fleet,
            defaults.engine.max_events_per_fleet);
  EXPECT_EQ(config.engine.limits.max_fleets, defaults.engine.limits.max_fleets);
  EXPECT_EQ(config.engine.limits.max_traces_per_fleet,
            defaults.engine.limits.max_traces_per_fleet);
  EXPECT_EQ(config.engine.limits.max_code_dimension,
            defaults.engine.limits.max_code_dimension);
  EXPECT_EQ(config.engine.limits.robot_traces_per_second,
            defaults.engine.limits.robot_traces_per_second);
  EXPECT_EQ(config.engine.limits.burst_seconds,
            defaults.engine.limits.burst_seconds);
  EXPECT_EQ(config.service.max_streams_per_client,
            defaults.service.max_streams_per_client);
  EXPECT_EQ(config.max_receive_message_bytes,
            defaults.max_receive_message_bytes);
  EXPECT_EQ(config.shutdown_grace_seconds, defaults.shutdown_grace_seconds);
  EXPECT_EQ(config.index_snapshot_interval_seconds,
            defaults.index_snapshot_interval_seconds);
  EXPECT_EQ(config.index_snapshot_min_codes, defaults.index_snapshot_min_codes);
  EXPECT_EQ(config.heap_trim_interval_seconds,
            defaults.heap_trim_interval_seconds);
  EXPECT_EQ(config.index, defaults.index);
  EXPECT_EQ(config.tiered.hnsw_from, defaults.tiered.hnsw_from);
  EXPECT_EQ(config.tiered.max_unindexed, defaults.tiered.max_unindexed);
  EXPECT_EQ(config.tiered.hnsw.ef_construction,
            defaults.tiered.hnsw.ef_construction);
  EXPECT_EQ(config.tiered.hnsw.insert_threads,
            defaults.tiered.hnsw.insert_threads);
  EXPECT_EQ(config.tiered.hnsw.codes, defaults.tiered.hnsw.codes);
  EXPECT_EQ(config.tiered.hnsw.rescore_oversample,
            defaults.tiered.hnsw.rescore_oversample);
  EXPECT_EQ(
      config.engine.fleet_memory.at("ablation-no-time-decay").replay_decay,
      1.0);
  EXPECT_EQ(config.write_path.max_backlog_traces,
            defaults.write_path.max_backlog_traces);
  EXPECT_EQ(config.write_path.appliers, defaults.write_path.appliers);
  EXPECT_EQ(config.write_path_max_apply_wait,
            defaults.write_path_max_apply_wait);
}

TEST(ServerConfigTest, WritePathFromTheFileIsValidated) {
  ServerConfig config;
  config.data_dir = "/tmp/d";
  ASSERT_TRUE(ApplyConfigText("write_path { max_backlog_traces: 1234 "
                              "appliers: 3 max_apply_wait_seconds: 7 "
                              "background_nice: 5 }",
                              &config)
                  .ok());
  EXPECT_EQ(config.write_path.max_backlog_traces, 1234u);
  EXPECT_EQ(config.write_path.appliers, 3);
  EXPECT_EQ(config.write_path_max_apply_wait, absl::Seconds(7));
  EXPECT_EQ(config.write_path.applier_nice, 5);
  EXPECT_EQ(config.tiered.indexer_nice, 5);
  EXPECT_TRUE(ValidateServerConfig(config).ok());
  for (const char* bad :
       {"write_path { appliers: 0 }", "write_path { appliers: 65 }",
        "write_path { max_apply_wait_seconds: 0 }",
        "write_path { background_nice: 20 }"}) {
    ServerConfig refused;
    refused.data_dir = "/tmp/d";
    ASSERT_TRUE(ApplyConfigText(bad, &refused).ok()) << bad;
    const absl::Status status = ValidateServerConfig(refused);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << bad;
    EXPECT_THAT(std::string(status.message()),
                ::testing::HasSubstr("write_path"))
        << bad;
  }
}

TEST(ServerConfigTest, BadFileText) {
  const char* cases[] = {
      "listen: ",                                // syntax
      "no_such_field: 1",                        // unknown field
      "memory { max_clusters: -x }",             // bad value
      "index: \"annoy\"",                        // unknown index
      "log_level: \"loud\"",                     // unknown level
      "index_snapshot_interval_seconds: 90000",  // over a day
      "heap_trim_interval_seconds: 90000",       // over a day
      "hnsw { codes: \"int4\" }",                // unknown codes
  };
  for (const char* text : cases) {
    ServerConfig config;
    absl::Status status = ApplyConfigText(text, &config);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << text;
  }
  ServerConfig config;
  absl::Status status = ApplyConfigText("\n\nbogus: 1", &config);
  EXPECT_NE(status.message().find("line 3"), std::string::npos) << status;
  status = ApplyConfigText("hnsw { codes: \"int4\" }", &config);
  EXPECT_NE(status.message().find("hnsw.codes"), std::string::npos) << status;
}

TEST(ServerConfigTest, GraphCodesFromTheFile) {
  ServerConfig config;
  EXPECT_EQ(config.tiered.hnsw.codes, index::HnswIndexOptions::Codes::kInt8);
  ASSERT_TRUE(ApplyConfigText("hnsw { codes: \"float\" rescore_oversample: 2 "
                              "indexer_batch: 3 }",
                              &config)
                  .ok());
  EXPECT_EQ(config.tiered.indexer_batch, 3u);
  EXPECT_EQ(config.tiered.hnsw.codes, index::HnswIndexOptions::Codes::kFloat);
  EXPECT_EQ(config.tiered.hnsw.rescore_oversample, 2u);
  EXPECT_NE(DescribeConfig(config).find("hnsw_codes=float"), std::string::npos)
      << DescribeConfig(config);
}

// Where int8 graphs keep their floats: a file per graph under the data
// dir by default, the heap with floats: "memory"; any other word refused.
TEST(ServerConfigTest, GraphFloatsFromTheFile) {
  absl::StatusOr<CommandLine> line = Parse({"--data-dir", "/tmp/fm-data"});
  ASSERT_TRUE(line.ok());
  absl::StatusOr<ServerConfig> loaded = LoadServerConfig(*line);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_TRUE(loaded->graph_floats_in_files);
  EXPECT_EQ(loaded->tiered.hnsw.floats_dir, "/tmp/fm-data/graph-floats");
  EXPECT_NE(DescribeConfig(*loaded).find("hnsw_floats=file"),
            std::string::npos);
  ServerConfig config;
  ASSERT_TRUE(ApplyConfigText("hnsw { floats: \"memory\" }", &config).ok());
  EXPECT_FALSE(config.graph_floats_in_files);
  EXPECT_NE(DescribeConfig(config).find("hnsw_floats=memory"),
            std::string::npos);
  const absl::Status bad =
      ApplyConfigText("hnsw { floats: \"disk\" }", &config);
  EXPECT_NE(bad.message().find("hnsw.floats"), std::string::npos) << bad;
  EXPECT_FALSE(config.graph_floats_in_files);
}

TEST(ServerConfigTest, Validation) {
  auto valid = [] {
    ServerConfig config;
    config.data_dir = "/tmp/d";
    return config;
  };
  EXPECT_TRUE(ValidateServerConfig(valid()).ok());

  struct Case {
    const char* name;
    void (*mutate)(ServerConfig&);
  };
  const Case cases[] = {
      {"no data dir", [](ServerConfig& c) { c.data_dir.clear(); }},
      {"no port", [](ServerConfig& c) { c.listen = "localhost"; }},
      {"port range", [](ServerConfig& c) { c.listen = "localhost:70000"; }},
      {"port text", [](ServerConfig& c) { c.listen = "localhost:http"; }},
      {"no host", [](ServerConfig& c) { c.listen = ":50051"; }},
      {"message size",
       [](ServerConfig& c) { c.max_receive_message_bytes = 0; }},
      {"queue", [](ServerConfig& c) { c.work.max_queued = 0; }},
      {"engine", [](ServerConfig& c) { c.engine.memory.max_clusters = 0; }},
      {"segment", [](ServerConfig& c) { c.engine.segment_size = 0; }},
      {"gamma", [](ServerConfig& c) { c.engine.memory.replay_decay = 1.5; }},
      {"no insert thread",
       [](ServerConfig& c) { c.tiered.hnsw.insert_threads = 0; }},
      {"insert threads",
       [](ServerConfig& c) { c.tiered.hnsw.insert_threads = 65; }},
      {"no rescoring",
       [](ServerConfig& c) { c.tiered.hnsw.rescore_oversample = 0; }},
      {"rescoring",
       [](ServerConfig& c) { c.tiered.hnsw.rescore_oversample = 65; }},
      {"indexer batch", [](ServerConfig& c) { c.tiered.indexer_batch = 65; }},
  };
  for (const Case& c : cases) {
    ServerConfig config = valid();
    c.mutate(config);
    EXPECT_EQ(ValidateServerConfig(config).code(),
              absl::StatusCode::kInvalidArgument)
        << c.name;
  }
}

TEST(ServerConfigTest, LoadWithoutFileUsesDefaultsAndFlags) {
  CommandLine flags;
  flags.data_dir = "/tmp/d";
  absl::StatusOr<ServerConfig> config = LoadServerConfig(flags);
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->listen, "127.0.0.1:50051");
  EXPECT_EQ(config->index, kDefaultIndex);
  EXPECT_EQ(config->max_receive_message_bytes, size_t{16} << 20);

  flags.config_file = "/nonexistent/fleetmem.textproto";
  EXPECT_EQ(LoadServerConfig(flags).status().code(),
            absl::StatusCode::kNotFound);

  CommandLine bad;
  bad.data_dir = "/tmp/d";
  bad.log_level = "verbose";
  EXPECT_EQ(LoadServerConfig(bad).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fleetmem::server

namespace fleetmem::server {
namespace {

TEST(ServerConfigTest, SecurityAndLimitsFromTheFileAndFlags) {
  ServerConfig config;
  ASSERT_TRUE(
      ApplyConfigText("data_dir: \"d\" listen: \"0.0.0.0:1\"\n"
                      "limits { robot_traces_per_second: 5 max_fleets: 2 "
                      "max_streams_per_client: 3 }\n"
                      "engine { max_events_per_fleet: 7 }\n"
                      "security { tls_cert_file: \"s.pem\" tls_key_file: "
                      "\"s.key\" }\n",
                      &config)
          .ok());
  EXPECT_EQ(config.engine.limits.robot_traces_per_second, 5);
  EXPECT_EQ(config.engine.limits.max_fleets, 2u);
  EXPECT_EQ(config.service.max_streams_per_client, 3u);
  EXPECT_EQ(config.engine.max_events_per_fleet, 7u);
  // Not loopback and no auth: refused until either is given.
  absl::Status open = ValidateServerConfig(config);
  EXPECT_EQ(open.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(open.message().find("--allow-unauthenticated"), std::string::npos);
  const char* argv[] = {"fleetmem-server", "--auth-file", "creds",
                        "--tls-client-ca", "ca.pem"};
  absl::StatusOr<CommandLine> flags = ParseCommandLine(5, argv);
  ASSERT_TRUE(flags.ok()) << flags.status();
  ASSERT_TRUE(ApplyCommandLine(*flags, &config).ok());
  EXPECT_TRUE(ValidateServerConfig(config).ok());
  EXPECT_EQ(config.security.auth_file, "creds");

  ServerConfig unpaired;
  unpaired.data_dir = "d";
  unpaired.security.tls_cert_file = "s.pem";
  EXPECT_FALSE(ValidateServerConfig(unpaired).ok());
  ServerConfig bad_rate;
  bad_rate.data_dir = "d";
  bad_rate.engine.limits.robot_traces_per_second = -1;
  EXPECT_FALSE(ValidateServerConfig(bad_rate).ok());
}

TEST(ServerConfigTest, LoopbackAddresses) {
  EXPECT_TRUE(IsLoopbackListen("127.0.0.1:1"));
  EXPECT_TRUE(IsLoopbackListen("127.9.9.9:0"));
  EXPECT_TRUE(IsLoopbackListen("localhost:5"));
  EXPECT_TRUE(IsLoopbackListen("[::1]:5"));
  EXPECT_FALSE(IsLoopbackListen("0.0.0.0:5"));
  EXPECT_FALSE(IsLoopbackListen("[::]:5"));
  EXPECT_FALSE(IsLoopbackListen("10.0.0.1:5"));
  const char* argv[] = {"fleetmem-server", "--allow-unauthenticated"};
  absl::StatusOr<CommandLine> flags = ParseCommandLine(2, argv);
  ASSERT_TRUE(flags.ok());
  EXPECT_TRUE(flags->allow_unauthenticated);
}

TEST(ServerConfigTest, HttpPortFlagsFileAndValidation) {
  absl::StatusOr<CommandLine> flags =
      Parse({"--data-dir", "/tmp/x", "--http-listen", "127.0.0.1:8080",
             "--snapshot-dir", "/backups", "--ready-file", "/run/fm.ready"});
  ASSERT_TRUE(flags.ok()) << flags.status();
  absl::StatusOr<ServerConfig> config = LoadServerConfig(*flags);
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_EQ(config->http_listen, "127.0.0.1:8080");
  EXPECT_EQ(config->snapshot_dir, "/backups");
  EXPECT_EQ(config->ready_file, "/run/fm.ready");

  ServerConfig file_config;
  ASSERT_TRUE(ApplyConfigText("http_listen: \"127.0.0.1:0\" "
                              "max_http_body_bytes: 65536",
                              &file_config)
                  .ok());
  EXPECT_EQ(file_config.http_listen, "127.0.0.1:0");
  EXPECT_EQ(file_config.max_http_body_bytes, 65536u);

  ServerConfig bad = *config;
  bad.http_listen = "nonsense";
  absl::Status status = ValidateServerConfig(bad);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("http_listen"), std::string::npos);
  bad.http_listen = "127.0.0.1:0";
  bad.max_http_body_bytes = 10;
  EXPECT_NE(ValidateServerConfig(bad).message().find("max_http_body_bytes"),
            std::string::npos);
  // Open HTTP on a non-loopback address is refused like open gRPC.
  ServerConfig open = *config;
  open.http_listen = "0.0.0.0:8080";
  status = ValidateServerConfig(open);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(status.message().find("http_listen: refusing"), std::string::npos);
  open.security.allow_unauthenticated = true;
  EXPECT_TRUE(ValidateServerConfig(open).ok());
}

TEST(ServerConfigTest, ClusterModeFromFlagsAndFileIsValidated) {
  absl::StatusOr<CommandLine> flags =
      Parse({"--data-dir", "/tmp/x", "--cluster",
             "nats://10.0.0.1:4222,nats://10.0.0.2:4222", "--advertise",
             "fleetmem-0.fleetmem:50051"});
  ASSERT_TRUE(flags.ok()) << flags.status();
  absl::StatusOr<ServerConfig> config = LoadServerConfig(*flags);
  ASSERT_TRUE(config.ok()) << config.status();
  EXPECT_TRUE(config->cluster.enabled());
  EXPECT_EQ(config->cluster.nats.servers,
            (std::vector<std::string>{"nats://10.0.0.1:4222",
                                      "nats://10.0.0.2:4222"}));
  EXPECT_EQ(config->cluster.advertise, "fleetmem-0.fleetmem:50051");
  EXPECT_EQ(config->cluster.nats.replicas, 3);
  EXPECT_EQ(config->cluster.nats.lease_ttl, absl::Seconds(5));

  ServerConfig file_config;
  ASSERT_TRUE(
      ApplyConfigText("cluster { servers: \"nats://n:4222\" advertise: \"r:1\" "
                      "replicas: 1 lease_ttl_ms: 2000 round_interval_ms: 50 "
                      "max_entry_bytes: 65536 peer_token_file: \"/t\" "
                      "snapshot_every_entries: 50 trim_log: false "
                      "balance_fleets: false }",
                      &file_config)
          .ok());
  EXPECT_EQ(file_config.cluster.nats.replicas, 1);
  EXPECT_EQ(file_config.cluster.nats.lease_ttl, absl::Seconds(2));
  EXPECT_EQ(file_config.cluster.round_interval, absl::Milliseconds(50));
  EXPECT_EQ(file_config.cluster.max_entry_bytes, 65536u);
  EXPECT_EQ(file_config.cluster.peer_token_file, "/t");
  EXPECT_EQ(file_config.cluster.snapshot_every_entries, 50u);
  EXPECT_FALSE(file_config.cluster.trim_log);
  EXPECT_FALSE(file_config.cluster.balance_fleets);
  EXPECT_TRUE(ServerConfig().cluster.balance_fleets);
  EXPECT_EQ(ServerConfig().cluster.snapshot_every_entries, 250u);
  EXPECT_TRUE(ServerConfig().cluster.trim_log);
  EXPECT_FALSE(ServerConfig().cluster.enabled());

  const auto refused = [&](ServerConfig bad, const std::string& says) {
    absl::Status status = ValidateServerConfig(bad);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << says;
    EXPECT_NE(status.message().find(says), std::string::npos) << status;
  };
  ServerConfig bad = *config;
  bad.cluster.advertise = "";
  refused(bad, "cluster.advertise");
  bad = *config;
  bad.cluster.advertise = "host:0";
  refused(bad, "cluster.advertise");
  bad = *config;
  bad.cluster.nats.lease_ttl = absl::Milliseconds(500);
  refused(bad, "lease TTL must be at least 1 s");
  bad = *config;
  bad.cluster.round_interval = absl::Seconds(2);
  refused(bad, "round_interval_ms");
  bad = *config;
  bad.cluster.nats.servers = {"http://x"};
  refused(bad, "cluster:");
  bad = *config;
  bad.security.auth_file = "/creds";
  refused(bad, "peer_token_file");
  // Upload rates are the receiving replica's (ClusterMode).
  ServerConfig rates = *config;
  rates.engine.limits.robot_traces_per_second = 10;
  EXPECT_TRUE(ValidateServerConfig(rates).ok());
}

// The configuration files shipped with the images, the compose fleet, the
// Docker tests and Kubernetes parse and validate: a typo there is caught
// here, not when a container starts.
std::string ReadSourceFile(const std::string& relative) {
  std::ifstream in(std::string(FLEETMEM_SOURCE_DIR) + "/" + relative);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

// The block scalar `key: |` of a YAML file, without its indentation.
std::string YamlBlock(const std::string& yaml, const std::string& key) {
  std::istringstream in(yaml);
  std::string line, block;
  size_t indent = std::string::npos;
  bool inside = false;
  while (std::getline(in, line)) {
    if (!inside) {
      inside = line.find(key + ": |") != std::string::npos;
      continue;
    }
    const size_t first = line.find_first_not_of(' ');
    if (first == std::string::npos) continue;
    if (indent == std::string::npos) indent = first;
    if (first < indent) break;
    block += line.substr(indent) + "\n";
  }
  return block;
}

TEST(ShippedConfigTest, EveryShippedServerConfigIsValid) {
  const std::vector<std::pair<std::string, std::string>> files = {
      {"docker/server.textproto", ReadSourceFile("docker/server.textproto")},
      {"docker/compose/server.textproto",
       ReadSourceFile("docker/compose/server.textproto")},
      {"tests/docker/server-test.textproto",
       ReadSourceFile("tests/docker/server-test.textproto")},
      {"k8s/overlays/example/server.textproto",
       ReadSourceFile("k8s/overlays/example/server.textproto")},
      {"k8s/base/server-configmap.yaml",
       YamlBlock(ReadSourceFile("k8s/base/server-configmap.yaml"),
                 "server.textproto")},
      {"docker/cluster/server.textproto",
       ReadSourceFile("docker/cluster/server.textproto")},
      {"k8s/overlays/cluster/server.textproto",
       ReadSourceFile("k8s/overlays/cluster/server.textproto")},
  };
  for (const auto& [name, text] : files) {
    SCOPED_TRACE(name);
    ASSERT_NE(text.find("listen:"), std::string::npos) << "empty: " << name;
    ServerConfig config;
    ASSERT_TRUE(ApplyConfigText(text, &config).ok())
        << ApplyConfigText(text, &config);
    EXPECT_EQ(config.listen, "0.0.0.0:50051");
    EXPECT_EQ(config.http_listen, "0.0.0.0:8080");
    // A replica's address comes from its command line (--advertise).
    if (name.find("cluster/") != std::string::npos) {
      EXPECT_TRUE(config.cluster.enabled());
      config.cluster.advertise = "fleetmem-0:50051";
    }
    // The image's own file has no credentials: it must be refused on
    // 0.0.0.0 (the server will not start open on a network); the others
    // turn auth and TLS on and are valid as they are.
    const absl::Status valid = ValidateServerConfig(config);
    if (name == "docker/server.textproto") {
      EXPECT_FALSE(valid.ok());
    } else {
      EXPECT_TRUE(valid.ok()) << valid;
      EXPECT_FALSE(config.security.auth_file.empty());
      EXPECT_FALSE(config.security.tls_cert_file.empty());
    }
  }
}

}  // namespace
}  // namespace fleetmem::server
