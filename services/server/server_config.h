// fleetmem-server's settings: defaults, the command line, the config file
// (protobuf text format of server_config.proto) and their validation. Flags
// override the file, the file overrides the defaults.
#ifndef FLEETMEM_SERVICES_SERVER_SERVER_CONFIG_H_
#define FLEETMEM_SERVICES_SERVER_SERVER_CONFIG_H_

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/common/log.h"
#include "services/engine/memory_engine.h"
#include "services/index/flann_index.h"
#include "services/storage/rocksdb_store.h"
#include "services/transport/work_queue.h"

namespace fleetmem::server {

enum class IndexKind { kExact, kFlann };

// The place index used when neither file nor flag names one. Exact is the
// reference (recall 1); switch here if the index benchmark favours FLANN.
inline constexpr IndexKind kDefaultIndex = IndexKind::kExact;

// "exact" / "flann"; false for anything else.
bool ParseIndexKind(std::string_view text, IndexKind* kind);
std::string_view IndexKindName(IndexKind kind);

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
  // Memory parameters and limits of the engine.
  engine::EngineOptions engine;
  // RocksDB tuning; `path` is ignored, the database is data_dir/db.
  storage::RocksDbStoreOptions storage;
  // Workers running engine calls and the length of their queue.
  transport::WorkQueueOptions work;
  // Largest request message accepted (gRPC answers RESOURCE_EXHAUSTED).
  size_t max_receive_message_bytes = size_t{16} << 20;
  // On SIGTERM/SIGINT, calls in flight get this long to finish.
  int shutdown_grace_seconds = 10;
};

// What the command line asked for; unset fields leave the file's or the
// default value.
struct CommandLine {
  bool help = false;
  std::optional<std::string> config_file;
  std::optional<std::string> listen;
  std::optional<std::string> data_dir;
  std::optional<std::string> log_level;
  std::optional<std::string> index;
};

// Parses argv[1..argc): --listen, --data-dir, --config, --log-level,
// --index as "--name=value" or "--name value"; --help or -h. INVALID_ARGUMENT
// for an unknown flag, a missing value or a positional argument.
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
// HOST:PORT, limits positive, engine options valid (ValidateEngineOptions).
// Otherwise INVALID_ARGUMENT naming the setting.
absl::Status ValidateServerConfig(const ServerConfig& config);

// Defaults, then the --config file (NOT_FOUND / INVALID_ARGUMENT if it
// cannot be read or parsed), then the flags; validated.
absl::StatusOr<ServerConfig> LoadServerConfig(const CommandLine& command_line);

// One line of "name=value" pairs for the start-up log.
std::string DescribeConfig(const ServerConfig& config);

}  // namespace fleetmem::server

#endif  // FLEETMEM_SERVICES_SERVER_SERVER_CONFIG_H_
