#include "clients/cli/cli.h"

#include <chrono>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "clients/cli/commands.h"
#include "clients/cli/flags.h"
#include "services/common/usage.h"

namespace fleetmem::cli {
namespace {

constexpr char kDefaultServer[] = "127.0.0.1:50051";
constexpr uint64_t kMaxDeadlineMs = 24ull * 3600 * 1000;

std::vector<FlagSpec> GlobalFlags() {
  return {{"server", "HOST:PORT",
           "server address (default $FLEETMEM_SERVER, else 127.0.0.1:50051)"},
          {"deadline-ms", "MS",
           "deadline of each attempt of a call (default 10000)"},
          {"json", "",
           "print responses as protobuf JSON (one per line) instead of tables"},
          {"token-file", "FILE",
           "file with the token NAME:SECRET (default $FLEETMEM_TOKEN_FILE, "
           "else the token in $FLEETMEM_TOKEN, else none)"},
          {"tls-ca", "FILE", "PEM of the server's CA: connect with TLS"},
          {"tls-cert", "FILE", "PEM client certificate (mutual TLS)"},
          {"tls-key", "FILE", "PEM key of --tls-cert"},
          {"tls-server-name", "NAME",
           "name expected in the server's certificate (default: the host)"},
          {"help", "", "print this help and exit (also -h)"},
          {"version", "", "print the version and exit"}};
}

CommandSpec HelpSpec() {
  return {"help", "[COMMAND]", "Show help for the tool or a command.", "", {}};
}

int ToolUsageError(const CliEnvironment& env, std::string_view message) {
  *env.err << common::UsageErrorText("fleetmem", message);
  return kExitUsage;
}

// The client options the global flags ask for.
absl::StatusOr<client::ClientOptions> ClientOptionsFrom(
    const FlagValues& global, const CliEnvironment& env) {
  client::ClientOptions options;
  options.target = global.StringOr("server", env.default_server.empty()
                                                 ? kDefaultServer
                                                 : env.default_server);
  if (options.target.empty()) {
    return absl::InvalidArgumentError("--server is empty");
  }
  absl::StatusOr<uint64_t> deadline_ms =
      global.UintOr("deadline-ms", options.deadline.count(), kMaxDeadlineMs);
  if (!deadline_ms.ok()) return deadline_ms.status();
  if (*deadline_ms == 0) {
    return absl::InvalidArgumentError("--deadline-ms must be positive");
  }
  options.deadline = std::chrono::milliseconds(*deadline_ms);
  client::CredentialSources sources;
  sources.token_file = global.StringOr("token-file", "");
  sources.ca_file = global.StringOr("tls-ca", "");
  sources.cert_file = global.StringOr("tls-cert", "");
  sources.key_file = global.StringOr("tls-key", "");
  if (absl::Status loaded = client::LoadCredentials(sources, &options);
      !loaded.ok()) {
    return loaded;
  }
  options.tls_server_name = global.StringOr("tls-server-name", "");
  return options;
}

}  // namespace

int RunCli(std::span<const std::string> args, const CliEnvironment& env) {
  std::vector<CommandSpec> specs = {HelpSpec()};
  for (const Command& command : Commands()) specs.push_back(command.spec);
  const std::vector<FlagSpec> global_flags = GlobalFlags();

  absl::StatusOr<CommandLine> line =
      ParseCommandLine(args, global_flags, specs);
  if (!line.ok())
    return ToolUsageError(env, std::string(line.status().message()));

  if (line->global.Has("version")) {
    *env.out << common::VersionLine("fleetmem");
    return kExitOk;
  }
  if (line->command.empty() || line->command == "help") {
    if (line->command.empty() && !line->help) {
      *env.err << FormatToolHelp(global_flags, specs);
      return kExitUsage;
    }
    if (line->positional.empty()) {
      *env.out << FormatToolHelp(global_flags, specs);
      return kExitOk;
    }
    for (const CommandSpec& spec : specs) {
      if (spec.name == line->positional.front()) {
        *env.out << FormatCommandHelp(spec, global_flags);
        return kExitOk;
      }
    }
    return ToolUsageError(
        env, absl::StrCat("unknown command '", line->positional.front(), "'"));
  }

  const Command* command = nullptr;
  for (const Command& candidate : Commands()) {
    if (candidate.spec.name == line->command) command = &candidate;
  }
  if (line->help) {
    *env.out << FormatCommandHelp(command->spec, global_flags);
    return kExitOk;
  }
  Invocation invocation;
  invocation.command = command->spec.name;
  invocation.flags = &line->flags;
  invocation.in = env.in;
  invocation.out = env.out;
  invocation.err = env.err;
  invocation.enable_stop = env.enable_stop;
  if (!line->positional.empty()) {
    return UsageError(invocation, absl::InvalidArgumentError(absl::StrCat(
                                      "unexpected argument '",
                                      line->positional.front(), "'")));
  }
  absl::StatusOr<client::ClientOptions> options =
      ClientOptionsFrom(line->global, env);
  if (!options.ok()) return UsageError(invocation, options.status());
  invocation.client_options = *std::move(options);
  invocation.json = line->global.Has("json");
  return command->run(invocation);
}

}  // namespace fleetmem::cli
