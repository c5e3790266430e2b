#include "clients/cli/commands.h"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <limits>
#include <memory>
#include <sstream>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "clients/cli/npy_writer.h"
#include "clients/cli/printing.h"
#include "clients/cli/synthetic_traces.h"
#include "clients/cli/trace_io.h"
#include "services/common/usage.h"

namespace fleetmem::cli {
namespace {

constexpr uint64_t kDefaultK = 5;
constexpr uint64_t kMaxK = 1000;
constexpr uint64_t kDefaultSampleCount = 10;
// How often a watch checks for Ctrl-C.
constexpr std::chrono::milliseconds kWatchPoll{200};
// Reconnection attempts of a watch in a row without an event: with backoff
// capped at 5 s, a watch outlives a server restart of a few minutes.
constexpr int kWatchMaxAttempts = 60;

FlagSpec FleetFlag() { return {"fleet", "ID", "fleet id (required)"}; }

// The command table (built once, never destroyed). Long (260 lines) by its
// nature: one entry per command with its help text, in --help's order.
const std::vector<Command>& CommandTable() {
  static const auto* const commands = new std::vector<Command>{
      {{"upload",
        "--fleet ID --file FILE",
        "Upload memory traces from a JSON Lines file.",
        "FILE holds one fleetmem.v1.MemoryTrace per line in protobuf JSON, "
        "e.g.\n"
        "  {\"robotId\":\"robot-1\",\"seq\":\"1\",\"domain\":\"summer\","
        "\"code\":[0.1,0.2],\n"
        "   \"pose\":{\"x\":1.5,\"y\":2},\"reward\":0.7,"
        "\"encoderVersion\":\"v1\"}\n"
        "('-' reads stdin; `fleetmem gen-traces` writes such files). Traces\n"
        "are sent in one stream; a retried upload is safe because the server\n"
        "stores each (robotId, seq) once. Prints how many traces were "
        "accepted\n"
        "and how many were duplicates (after a retry, duplicates may include\n"
        "traces that an earlier failed attempt of the same upload stored).",
        {FleetFlag(),
         {"file", "FILE",
          "JSON Lines file of traces, '-' for stdin (required)"}}},
       RunUpload},
      {{"query",
        "--fleet ID (--code-file FILE | --code LIST) [--k N] "
        "[--near X,Y[,Z] --radius M]",
        "Find the k traces of the fleet's memory nearest to a code.",
        "The code comes from --code (numbers separated by commas) or from\n"
        "--code-file: a JSON array of numbers, or a JSON object with a "
        "\"code\"\n"
        "array (a QueryPlaceRequest, or one line of a traces file; '-' reads\n"
        "stdin). Flags override k/near/radiusM given in the file.",
        {FleetFlag(),
         {"code", "LIST", "query code, e.g. \"0.1,0.2,0.3\""},
         {"code-file", "FILE", "JSON file holding the query code"},
         {"k", "N", "matches wanted, 1..1000 (default 5)"},
         {"near", "X,Y[,Z]", "position prior in metres (needs --radius)"},
         {"radius", "M", "only matches within M metres of --near"}}},
       RunQuery},
      {{"sample",
        "--fleet ID --robot ROBOT [--count N]",
        "Draw traces for a robot's replay (importance sampling).",
        "Not retried: each call increments the replay counts of the traces\n"
        "it returns.",
        {FleetFlag(),
         {"robot", "ROBOT", "robot refreshing its memory (required)"},
         {"count", "N", "traces wanted (default 10)"}}},
       RunSample},
      {{"stats",
        "--fleet ID",
        "Show the fleet's memory, robots and domains.",
        "",
        {FleetFlag()}},
       RunStats},
      {{"health",
        "[--service NAME]",
        "Ask the server's gRPC health service (grpc.health.v1).",
        "Prints the serving status (SERVING, NOT_SERVING, SERVICE_UNKNOWN) "
        "and\n"
        "exits 0 only for SERVING: a probe for Kubernetes or Docker. Needs no\n"
        "credential; one attempt within --deadline.",
        {{"service", "NAME", "a service's full name (default: the server)"}}},
       RunHealth},
      {{"consolidate",
        "--fleet ID",
        "Consolidate all pending traces now (clustering, then forgetting).",
        "",
        {FleetFlag()}},
       RunConsolidate},
      {{"watch",
        "--fleet ID [--after ID] [--max-events N]",
        "Stream memory events (clusters added and forgotten).",
        "Prints the events after --after (0: the whole history), then live\n"
        "ones, until --max-events were printed or Ctrl-C. Reconnects after a\n"
        "broken stream (e.g. a server restart) without missing or repeating\n"
        "events; gives up after 60 failed reconnections in a row (backoff up\n"
        "to 5 s, a few minutes). On exit prints the last event id on stderr\n"
        "(resume with --after ID). With --json, one JSON object per line.",
        {FleetFlag(),
         {"after", "ID", "start after this event id (default 0)"},
         {"max-events", "N", "stop after N events (default 0: no limit)"}}},
       RunWatch},
      {{"gen-traces",
        "--robots N --per-robot M --dim D [--seed S] [--encoder V] "
        "[--out FILE]",
        "Write SYNTHETIC traces as JSON Lines (for docs and smoke tests).",
        "The traces are made up, not recorded: every robot drives the same\n"
        "loop of M places 5 m apart in its own domain (summer, fall, winter,\n"
        "spring in turn); a code is the place's prototype plus a domain shift\n"
        "and noise, L2-normalised, so the same place seen by two robots gives\n"
        "nearby codes. Rewards are random. Same seed, same output. Does not\n"
        "contact the server.",
        {{"robots", "N", "robots robot-1..robot-N (default 3)"},
         {"per-robot", "M", "traces per robot, seq 1..M (default 100)"},
         {"dim", "D", "code dimension (default 256)"},
         {"seed", "S", "random seed (default 1)"},
         {"encoder", "V", "encoderVersion of the traces (default v1)"},
         {"out", "FILE", "output file (default stdout)"}}},
       RunGenTraces},
      {{"fleets",
        "",
        "List the fleets the caller may see, with their counts.",
        "",
        {}},
       RunFleets},
      {{"clusters",
        "--fleet ID [--places]",
        "List the static memory's clusters (centroid, size, robots, "
        "domains).",
        "With --places and --json, every trace's place is listed too.",
        {FleetFlag(),
         {"places", "", "include each trace's place (with --json)"}}},
       RunClusters},
      {{"snapshot",
        "--name NAME",
        "Admin: write a consistent snapshot of the whole store.",
        "The server writes a RocksDB checkpoint to SNAPSHOT_DIR/NAME (its\n"
        "--snapshot-dir, DATA_DIR/snapshots by default) while it keeps\n"
        "serving; every write acknowledged before the call is in it. Start a\n"
        "server with --data-dir SNAPSHOT_DIR/NAME to serve exactly that "
        "state.",
        {{"name", "NAME", "snapshot name, [A-Za-z0-9._-] (required)"}}},
       RunSnapshot},
      {{"export",
        "--fleet ID --out DIR [--page-size N]",
        "Write the fleet's codes and places as .npy arrays plus a CSV.",
        "DIR/codes.npy    float32 N x D, one row per trace\n"
        "DIR/places.npy   float64 N x 4: x, y, z, yaw (metres, radians)\n"
        "DIR/metadata.csv row, robot_id, seq, domain, reward, "
        "reward_external,\n"
        "                 reward_internal, timestamp_ns, replay_count,\n"
        "                 cluster_id (0: pending), encoder_version\n"
        "Rows are in (robot_id, seq) order, read page by page from the live\n"
        "memory (progress on stderr); for a frozen state, export from a\n"
        "server started on a snapshot.",
        {FleetFlag(),
         {"out", "DIR", "output directory, created if missing (required)"},
         {"page-size", "N", "traces per request, 1..10000 (default 1000)"}}},
       RunExport},
      {{"import",
        "--fleet ID --from DIR [--chunk N] [--resume] [--robot R] "
        "[--encoder V]",
        "Admin: bulk-import .npy arrays (the export's) into a new fleet.",
        "DIR/codes.npy    float32 or float64, N x D\n"
        "DIR/places.npy   N x 2..4: x, y[, z[, yaw]] (the rest 0)\n"
        "DIR/metadata.csv the export's: robot_id, seq and reward per row\n"
        "                 (domain, reward_external, reward_internal,\n"
        "                 timestamp_ns, encoder_version where present)\n"
        "or, without it,\n"
        "DIR/rewards.npy  N rewards; the rows are robot --robot's, seqs 1..N\n"
        "Chunks of rows go to the server one ImportTraces call each (durable\n"
        "when answered, checked as uploads); the fleet's place graph is\n"
        "built once, by the last call, from every code. Replay counts and\n"
        "clusters are not imported: the fleet consolidates the traces anew.\n"
        "A fleet that holds traces is refused unless --resume (an import\n"
        "that stopped: the rows it holds count as duplicates).",
        {FleetFlag(),
         {"from", "DIR", "directory of the arrays (required)"},
         {"chunk", "N",
          "rows per call, 1..100000 (default: 8 MiB of codes, at most "
          "10000)"},
         {"resume", "", "go on with an import into a fleet holding traces"},
         {"robot", "R", "robot id of rows without metadata (default import)"},
         {"encoder", "V", "encoder version of rows without one"}}},
       RunImport},
      {{"create-fleet",
        "--fleet ID --dim D [--encoder V] [--place-unit U] [SETTINGS]",
        "Admin: make a fleet with its own settings.",
        "SETTINGS, each optional (the server's otherwise):\n"
        "  --clusters-per-segment K  --max-traces-per-cluster N\n"
        "  --max-clusters K_MAX      --replay-decay GAMMA\n"
        "  --forgetting merge|drop   --max-age-seconds S\n"
        "  --max-traces-per-robot N  --refresh-pairs RADIUS\n"
        "  --refresh-uniform true|false\n"
        "  --index exact|hnsw|auto   --hnsw-m M  --hnsw-ef EF\n"
        "  --hnsw-codes int8|float (fixed)\n"
        "Every upload must match --dim and --encoder. ALREADY_EXISTS if the\n"
        "fleet exists (made by create-fleet or its first upload).",
        {FleetFlag(),
         {"dim", "D", "code dimension (required)"},
         {"encoder", "V", "encoder version of its codes"},
         {"place-unit", "U", "unit of its places, e.g. m"},
         {"clusters-per-segment", "K", "K, clusters per segment"},
         {"max-traces-per-cluster", "N", "N_max, traces per cluster"},
         {"max-clusters", "K_MAX", "K_max, clusters before forgetting"},
         {"replay-decay", "GAMMA", "gamma of the replay weights, (0, 1]"},
         {"forgetting", "RULE", "merge (default) or drop"},
         {"max-age-seconds", "S", "retention: delete traces older than S"},
         {"max-traces-per-robot", "N", "retention: keep N per robot"},
         {"refresh-pairs", "RADIUS",
          "pair-keeping refresh within RADIUS place units (0: Eq. 18)"},
         {"refresh-uniform", "BOOL", "refresh with weight 1, not gamma^n R"},
         {"index", "KIND", "exact, hnsw or auto (default: the server's)"},
         {"hnsw-m", "M", "HNSW's links per node, 2..128"},
         {"hnsw-ef", "EF", "HNSW's search breadth, 1..10000"},
         {"hnsw-codes", "CODES",
          "int8 or float: what the graph walks on (default: the "
          "server's)"}}},
       RunCreateFleet},
      {{"fleet",
        "--fleet ID",
        "Show a fleet's settings and counts.",
        "",
        {FleetFlag()}},
       RunFleet},
      {{"update-fleet",
        "--fleet ID [SETTINGS]",
        "Admin: change a fleet's settings (those of create-fleet).",
        "A smaller --max-clusters or --max-traces-per-cluster applies at the\n"
        "next consolidation. The dimension, encoder and place unit are fixed\n"
        "at creation.",
        {FleetFlag(),
         {"clusters-per-segment", "K", "K, clusters per segment"},
         {"max-traces-per-cluster", "N", "N_max, traces per cluster"},
         {"max-clusters", "K_MAX", "K_max, clusters before forgetting"},
         {"replay-decay", "GAMMA", "gamma of the replay weights, (0, 1]"},
         {"forgetting", "RULE", "merge or drop"},
         {"max-age-seconds", "S", "retention: delete traces older than S"},
         {"max-traces-per-robot", "N", "retention: keep N per robot"},
         {"refresh-pairs", "RADIUS",
          "pair-keeping refresh within RADIUS place units (0: Eq. 18)"},
         {"refresh-uniform", "BOOL", "refresh with weight 1, not gamma^n R"}}},
       RunUpdateFleet},
      {{"delete-fleet",
        "--fleet ID --confirm ID",
        "Admin: delete a fleet and everything it holds.",
        "Its traces, clusters, robots' records, events, settings and index\n"
        "snapshot leave the server's disk, after every upload acknowledged\n"
        "before the call. --confirm must repeat the fleet's id. Refused while\n"
        "an alias names the fleet. An upload to the id afterwards makes a new\n"
        "fleet.",
        {FleetFlag(), {"confirm", "ID", "the fleet's id again (required)"}}},
       RunDeleteFleet},
      {{"aliases",
        "",
        "List the fleet aliases (those of the fleets the caller may see).",
        "",
        {}},
       RunAliases},
      {{"create-alias",
        "--alias NAME --fleet ID",
        "Admin: make NAME a name of fleet ID in every call.",
        "Every call that names a fleet accepts NAME in its place and reads\n"
        "and writes the fleet it names when the call starts. NAME may not be\n"
        "a fleet's id; ID must be a fleet, not an alias.",
        {{"alias", "NAME", "the alias (required)"}, FleetFlag()}},
       RunCreateAlias},
      {{"switch-alias",
        "--alias NAME --fleet ID",
        "Admin: point an alias at another fleet, in one step.",
        "Calls that start after the answer use the new fleet; a call or a\n"
        "stream that started before stays on the old one. The encoder\n"
        "migration in docs/api.md switches an alias once the new fleet holds\n"
        "what the robots re-encoded.",
        {{"alias", "NAME", "the alias (required)"}, FleetFlag()}},
       RunSwitchAlias},
      {{"delete-alias",
        "--alias NAME",
        "Admin: remove an alias (its fleet stays).",
        "",
        {{"alias", "NAME", "the alias (required)"}}},
       RunDeleteAlias},
      {{"delete-traces",
        "--fleet ID (--robot ROBOT [--seq-first N] [--seq-last N] | "
        "--domain D | --time-from NS | --time-to NS)...",
        "Delete every trace that matches all the criteria given.",
        "At least one criterion; --seq-first/--seq-last need --robot; times\n"
        "are observation times in ns since the epoch, [FROM, TO). Applied\n"
        "after every upload acknowledged before it, in one step; deleted\n"
        "traces are never returned again, and an upload of one again counts\n"
        "as a duplicate. An admin deletes any robot's traces, a robot only\n"
        "its own (--robot naming itself).",
        {FleetFlag(),
         {"robot", "ROBOT", "one robot's traces"},
         {"domain", "D", "traces of this domain"},
         {"seq-first", "N", "the robot's seqs from N (inclusive)"},
         {"seq-last", "N", "the robot's seqs up to N (inclusive)"},
         {"time-from", "NS", "observed at or after NS"},
         {"time-to", "NS", "observed before NS"}}},
       RunDeleteTraces},
      {{"update-rewards",
        "--fleet ID --file FILE",
        "Set R_ex and R_in of held traces (re-scoring).",
        "FILE holds one fleetmem.v1.RewardUpdate per line in protobuf JSON,\n"
        "e.g. {\"robotId\":\"robot-1\",\"seq\":\"7\","
        "\"rewardExternal\":0.4,\"rewardInternal\":0.1}\n"
        "('-' reads stdin; at most 10,000 lines). The next SampleReplay\n"
        "draws with R = R_ex + R_in. Prints how many traces were updated and\n"
        "which ones the fleet does not hold.",
        {FleetFlag(),
         {"file", "FILE",
          "JSON Lines file of reward updates, '-' for stdin (required)"}}},
       RunUpdateRewards},
      {{"get-traces",
        "--fleet ID --keys ROBOT:SEQ[,ROBOT:SEQ...]",
        "Fetch traces by (robot, seq), with their codes (--json).",
        "Prints the traces held, in the order named, and the keys the fleet\n"
        "does not hold.",
        {FleetFlag(),
         {"keys", "LIST", "comma-separated ROBOT:SEQ keys (required)"}}},
       RunGetTraces},
  };
  return *commands;
}

// Reads all of FILE, or of stdin for "-".
absl::StatusOr<std::string> ReadAll(const Invocation& invocation,
                                    const std::string& path) {
  if (path == "-") {
    return std::string(std::istreambuf_iterator<char>(*invocation.in), {});
  }
  std::ifstream file(path);
  if (!file) return absl::InvalidArgumentError("cannot open " + path);
  return std::string(std::istreambuf_iterator<char>(file), {});
}

// Sets the position prior of `request` from --near/--radius.
absl::Status SetPrior(const FlagValues& flags, v1::QueryPlaceRequest* request) {
  if (flags.Has("near") != flags.Has("radius")) {
    return absl::InvalidArgumentError("--near and --radius go together");
  }
  if (!flags.Has("near")) return absl::OkStatus();
  absl::StatusOr<std::vector<double>> near = flags.RequiredList("near");
  if (!near.ok()) return near.status();
  if (near->size() < 2 || near->size() > 3) {
    return absl::InvalidArgumentError("--near wants X,Y or X,Y,Z");
  }
  absl::StatusOr<double> radius = flags.RequiredDouble("radius");
  if (!radius.ok()) return radius.status();
  if (*radius <= 0) {
    return absl::InvalidArgumentError("--radius must be positive");
  }
  request->mutable_near()->set_x((*near)[0]);
  request->mutable_near()->set_y((*near)[1]);
  request->mutable_near()->set_z(near->size() == 3 ? (*near)[2] : 0.0);
  request->set_radius_m(*radius);
  return absl::OkStatus();
}

// The QueryPlaceRequest described by the flags.
absl::StatusOr<v1::QueryPlaceRequest> QueryFromFlags(
    const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return fleet.status();
  if (flags.Has("code") == flags.Has("code-file")) {
    return absl::InvalidArgumentError("give one of --code or --code-file");
  }
  v1::QueryPlaceRequest request;
  if (flags.Has("code-file")) {
    absl::StatusOr<std::string> path = flags.Required("code-file");
    if (!path.ok()) return path.status();
    absl::StatusOr<std::string> json = ReadAll(invocation, *path);
    if (!json.ok()) return json.status();
    absl::StatusOr<v1::QueryPlaceRequest> parsed = ParseQueryJson(*json);
    if (!parsed.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat(*path, ": ", parsed.status().message()));
    }
    request = *std::move(parsed);
  } else {
    absl::StatusOr<std::vector<double>> code = flags.RequiredList("code");
    if (!code.ok()) return code.status();
    for (double value : *code) request.add_code(static_cast<float>(value));
  }
  request.set_fleet_id(*fleet);
  absl::StatusOr<uint64_t> k =
      flags.UintOr("k", request.k() != 0 ? request.k() : kDefaultK, kMaxK);
  if (!k.ok()) return k.status();
  if (*k == 0) return absl::InvalidArgumentError("--k must be 1..1000");
  request.set_k(static_cast<uint32_t>(*k));
  if (absl::Status prior = SetPrior(flags, &request); !prior.ok()) {
    return prior;
  }
  return request;
}

}  // namespace

std::span<const Command> Commands() { return CommandTable(); }

int UsageError(const Invocation& invocation, const absl::Status& status) {
  *invocation.err << common::UsageErrorText(
      absl::StrCat("fleetmem ", invocation.command),
      std::string(status.message()));
  return kExitUsage;
}

int ServerError(const Invocation& invocation, const absl::Status& status) {
  *invocation.err << "error: " << absl::StatusCodeToString(status.code())
                  << ": " << status.message() << "\n";
  return kExitServerError;
}

int RunUpload(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> path = flags.Required("file");
  if (!path.ok()) return UsageError(invocation, path.status());
  absl::StatusOr<std::vector<v1::MemoryTrace>> traces;
  if (*path == "-") {
    traces = ReadTracesJsonl(*invocation.in);
  } else {
    std::ifstream file(*path);
    if (!file) {
      return UsageError(invocation,
                        absl::InvalidArgumentError("cannot open " + *path));
    }
    traces = ReadTracesJsonl(file);
  }
  if (!traces.ok()) {
    return UsageError(invocation, absl::InvalidArgumentError(absl::StrCat(
                                      *path, ": ", traces.status().message())));
  }
  absl::StatusOr<v1::UploadTracesResponse> response =
      Connect(invocation)->Upload(*fleet, *traces);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(invocation, *response, PrintUpload);
}

int RunQuery(const Invocation& invocation) {
  absl::StatusOr<v1::QueryPlaceRequest> request = QueryFromFlags(invocation);
  if (!request.ok()) return UsageError(invocation, request.status());
  absl::StatusOr<v1::QueryPlaceResponse> response =
      Connect(invocation)->Query(*request);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(
      invocation, *response,
      [](const v1::QueryPlaceResponse& answer, std::ostream& out) {
        const std::vector<v1::PlaceMatch> matches(answer.matches().begin(),
                                                  answer.matches().end());
        PrintMatches(matches, out);
      });
}

int RunSample(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> robot = flags.Required("robot");
  if (!robot.ok()) return UsageError(invocation, robot.status());
  absl::StatusOr<uint64_t> count =
      flags.UintOr("count", kDefaultSampleCount, UINT32_MAX);
  if (!count.ok()) return UsageError(invocation, count.status());
  if (*count == 0) {
    return UsageError(invocation,
                      absl::InvalidArgumentError("--count must be positive"));
  }
  absl::StatusOr<std::vector<v1::MemoryTrace>> traces =
      Connect(invocation)
          ->SampleReplay(*fleet, *robot, static_cast<uint32_t>(*count));
  if (!traces.ok()) return ServerError(invocation, traces.status());
  if (invocation.json) {
    v1::SampleReplayResponse response;
    for (v1::MemoryTrace& trace : *traces) {
      *response.add_traces() = std::move(trace);
    }
    PrintJson(response, /*pretty=*/false, *invocation.out);
  } else {
    PrintTraces(*traces, *invocation.out);
  }
  return kExitOk;
}

int RunStats(const Invocation& invocation) {
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<v1::GetStatsResponse> stats =
      Connect(invocation)->GetStats(*fleet);
  if (!stats.ok()) return ServerError(invocation, stats.status());
  return PrintResponse(invocation, *stats, PrintStats);
}

int RunHealth(const Invocation& invocation) {
  const std::string service = invocation.flags->Has("service")
                                  ? *invocation.flags->Required("service")
                                  : std::string();
  absl::StatusOr<std::string> status =
      Connect(invocation)->CheckHealth(service);
  if (!status.ok()) return ServerError(invocation, status.status());
  *invocation.out << *status << "\n";
  return *status == "SERVING" ? kExitOk : kExitServerError;
}

int RunConsolidate(const Invocation& invocation) {
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<v1::ConsolidateResponse> response =
      Connect(invocation)->Consolidate(*fleet);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(invocation, *response, PrintConsolidate);
}

int RunWatch(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<uint64_t> after = flags.UintOr("after", 0);
  if (!after.ok()) return UsageError(invocation, after.status());
  absl::StatusOr<uint64_t> max_events = flags.UintOr("max-events", 0);
  if (!max_events.ok()) return UsageError(invocation, max_events.status());
  const std::atomic<bool>* stop =
      invocation.enable_stop ? invocation.enable_stop() : nullptr;
  client::ClientOptions options = invocation.client_options;
  options.max_attempts = std::max(options.max_attempts, kWatchMaxAttempts);
  uint64_t printed = 0;
  auto print_event = [&](const v1::MemoryEvent& event) {
    if (invocation.json) {
      PrintJson(event, /*pretty=*/false, *invocation.out);
      invocation.out->flush();
    } else {
      PrintEvent(event, *invocation.out);
    }
    ++printed;
    return *max_events == 0 || printed < *max_events;
  };
  absl::StatusOr<uint64_t> last = client::Client::Create(options)->Watch(
      *fleet, *after, print_event, stop, kWatchPoll);
  if (!last.ok()) return ServerError(invocation, last.status());
  *invocation.err << "last event id: " << *last << " (resume with --after "
                  << *last << ")\n";
  return kExitOk;
}

int RunGenTraces(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  SyntheticTraceOptions options;
  absl::StatusOr<uint64_t> robots = flags.UintOr("robots", 3, 100'000);
  absl::StatusOr<uint64_t> per_robot =
      flags.UintOr("per-robot", 100, 10'000'000);
  absl::StatusOr<uint64_t> dimension = flags.UintOr("dim", 256, 65'536);
  absl::StatusOr<uint64_t> seed = flags.UintOr("seed", 1);
  for (const auto* value : {&robots, &per_robot, &dimension, &seed}) {
    if (!value->ok()) return UsageError(invocation, value->status());
  }
  if (*robots == 0 || *per_robot == 0 || *dimension == 0) {
    return UsageError(invocation,
                      absl::InvalidArgumentError(
                          "--robots, --per-robot and --dim must be positive"));
  }
  options.robots = static_cast<int>(*robots);
  options.per_robot = static_cast<int>(*per_robot);
  options.dimension = static_cast<int>(*dimension);
  options.seed = *seed;
  options.encoder_version = flags.StringOr("encoder", "v1");
  const std::vector<v1::MemoryTrace> traces = GenerateSyntheticTraces(options);

  const std::string path = flags.StringOr("out", "-");
  std::ofstream file;
  std::ostream* out = invocation.out;
  if (path != "-") {
    file.open(path);
    if (!file) {
      return UsageError(invocation,
                        absl::InvalidArgumentError("cannot write " + path));
    }
    out = &file;
  }
  if (absl::Status written = WriteTracesJsonl(traces, *out); !written.ok()) {
    return UsageError(invocation, written);
  }
  *invocation.err << "wrote " << traces.size() << " synthetic traces ("
                  << options.robots << " robots x " << options.per_robot
                  << ", dim " << options.dimension << ")"
                  << (path == "-" ? "" : " to " + path) << "\n";
  return kExitOk;
}

int RunFleets(const Invocation& invocation) {
  absl::StatusOr<v1::ListFleetsResponse> fleets =
      Connect(invocation)->ListFleets();
  if (!fleets.ok()) return ServerError(invocation, fleets.status());
  return PrintResponse(invocation, *fleets, PrintFleets);
}

int RunClusters(const Invocation& invocation) {
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<v1::ListClustersResponse> clusters =
      Connect(invocation)
          ->ListClusters(*fleet, invocation.flags->Has("places"));
  if (!clusters.ok()) return ServerError(invocation, clusters.status());
  return PrintResponse(invocation, *clusters, PrintClusters);
}

int RunSnapshot(const Invocation& invocation) {
  absl::StatusOr<std::string> name = invocation.flags->Required("name");
  if (!name.ok()) return UsageError(invocation, name.status());
  *invocation.err << "taking snapshot " << *name << " ..." << std::endl;
  absl::StatusOr<v1::CreateSnapshotResponse> snapshot =
      Connect(invocation)->CreateSnapshot(*name);
  if (!snapshot.ok()) return ServerError(invocation, snapshot.status());
  return PrintResponse(invocation, *snapshot, PrintSnapshot);
}

int RunExport(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> out = flags.Required("out");
  if (!out.ok()) return UsageError(invocation, out.status());
  absl::StatusOr<uint64_t> page_size = flags.UintOr("page-size", 1000, 10000);
  if (!page_size.ok()) return UsageError(invocation, page_size.status());
  if (*page_size == 0) {
    return UsageError(
        invocation, absl::InvalidArgumentError("--page-size must be positive"));
  }
  std::error_code error;
  std::filesystem::create_directories(*out, error);
  if (error) {
    return UsageError(invocation,
                      absl::InvalidArgumentError(absl::StrCat(
                          "cannot create ", *out, ": ", error.message())));
  }
  std::unique_ptr<client::Client> client = Connect(invocation);
  std::vector<float> codes;
  std::vector<double> places;
  std::ostringstream csv;
  csv << "row,robot_id,seq,domain,reward,reward_external,reward_internal,"
         "timestamp_ns,replay_count,cluster_id,encoder_version\n";
  size_t rows = 0;
  size_t dimension = 0;
  std::string token;
  do {
    absl::StatusOr<v1::ListTracesResponse> page =
        client->ListTraces(*fleet, static_cast<uint32_t>(*page_size), token);
    if (!page.ok()) {
      *invocation.err << "export stopped after " << rows
                      << " traces; nothing was written to " << *out << "\n";
      return ServerError(invocation, page.status());
    }
    for (const v1::MemoryTrace& trace : page->traces()) {
      if (rows == 0) dimension = static_cast<size_t>(trace.code_size());
      if (static_cast<size_t>(trace.code_size()) != dimension) {
        return ServerError(
            invocation,
            absl::DataLossError(absl::StrCat(
                "trace ", trace.robot_id(), "/", trace.seq(), " has dimension ",
                trace.code_size(), ", earlier ones ", dimension)));
      }
      codes.insert(codes.end(), trace.code().begin(), trace.code().end());
      places.insert(places.end(), {trace.pose().x(), trace.pose().y(),
                                   trace.pose().z(), trace.pose().yaw()});
      // Ids and domains are [A-Za-z0-9._:-]: no CSV quoting needed.
      csv << rows << ',' << trace.robot_id() << ',' << trace.seq() << ','
          << trace.domain() << ',' << trace.reward() << ','
          << trace.reward_external() << ',' << trace.reward_internal() << ','
          << trace.timestamp_ns() << ',' << trace.replay_count() << ','
          << trace.cluster_id() << ',' << trace.encoder_version() << '\n';
      ++rows;
    }
    *invocation.err << "\rexported " << rows << " / " << page->total_traces()
                    << " traces" << std::flush;
    token = page->next_page_token();
  } while (!token.empty());
  *invocation.err << "\n";
  const std::filesystem::path dir(*out);
  for (absl::Status written :
       {WriteNpy((dir / "codes.npy").string(), codes, rows, dimension),
        WriteNpy((dir / "places.npy").string(), places, rows, 4)}) {
    if (!written.ok()) return ServerError(invocation, written);
  }
  std::ofstream metadata(dir / "metadata.csv", std::ios::trunc);
  metadata << csv.str();
  metadata.flush();
  if (!metadata) {
    return ServerError(invocation,
                       absl::InternalError(absl::StrCat(
                           "cannot write ", (dir / "metadata.csv").string())));
  }
  *invocation.out << "wrote " << rows << " traces (dimension " << dimension
                  << ") to " << *out
                  << ": codes.npy, places.npy, metadata.csv\n";
  return kExitOk;
}

int RunDeleteTraces(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  v1::DeleteTracesRequest request;
  request.set_fleet_id(*fleet);
  request.set_robot_id(flags.StringOr("robot", ""));
  request.set_domain(flags.StringOr("domain", ""));
  for (const char* name : {"seq-first", "seq-last", "time-from", "time-to"}) {
    if (!flags.Has(name)) continue;
    absl::StatusOr<uint64_t> value =
        flags.RequiredUint(name, std::numeric_limits<int64_t>::max());
    if (!value.ok()) return UsageError(invocation, value.status());
    const absl::string_view flag = name;
    if (flag == "seq-first") request.set_seq_first(*value);
    if (flag == "seq-last") request.set_seq_last(*value);
    if (flag == "time-from") request.set_time_from_ns(*value);
    if (flag == "time-to") request.set_time_to_ns(*value);
  }
  absl::StatusOr<v1::DeleteTracesResponse> response =
      Connect(invocation)->DeleteTraces(request);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(invocation, *response, PrintDelete);
}

int RunUpdateRewards(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> file = flags.Required("file");
  if (!file.ok()) return UsageError(invocation, file.status());
  absl::StatusOr<std::string> text = ReadAll(invocation, *file);
  if (!text.ok()) return UsageError(invocation, text.status());
  std::istringstream lines(*text);
  absl::StatusOr<std::vector<v1::RewardUpdate>> updates =
      ReadRewardUpdatesJsonl(lines);
  if (!updates.ok()) return UsageError(invocation, updates.status());
  v1::UpdateRewardsRequest request;
  request.set_fleet_id(*fleet);
  for (v1::RewardUpdate& update : *updates) {
    *request.add_updates() = std::move(update);
  }
  absl::StatusOr<v1::UpdateRewardsResponse> response =
      Connect(invocation)->UpdateRewards(request);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(invocation, *response, PrintRewards);
}

int RunGetTraces(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> keys = flags.Required("keys");
  if (!keys.ok()) return UsageError(invocation, keys.status());
  v1::GetTracesRequest request;
  request.set_fleet_id(*fleet);
  for (absl::string_view key :
       absl::StrSplit(*keys, ',', absl::SkipWhitespace())) {
    const size_t colon = key.rfind(':');
    uint64_t seq = 0;
    if (colon == absl::string_view::npos ||
        !absl::SimpleAtoi(key.substr(colon + 1), &seq)) {
      return UsageError(invocation,
                        absl::InvalidArgumentError(absl::StrCat(
                            "--keys: \"", key, "\" is not ROBOT:SEQ")));
    }
    v1::TraceKey* out = request.add_keys();
    out->set_robot_id(std::string(key.substr(0, colon)));
    out->set_seq(seq);
  }
  absl::StatusOr<v1::GetTracesResponse> response =
      Connect(invocation)->GetTraces(request);
  if (!response.ok()) return ServerError(invocation, response.status());
  if (invocation.json) {
    PrintJson(*response, /*pretty=*/false, *invocation.out);
    return kExitOk;
  }
  PrintTraces(std::vector<v1::MemoryTrace>(response->traces().begin(),
                                           response->traces().end()),
              *invocation.out);
  for (const v1::TraceKey& key : response->missing()) {
    *invocation.out << "not held: " << key.robot_id() << ":" << key.seq()
                    << "\n";
  }
  return kExitOk;
}

namespace {

// The settings flags of create-fleet and update-fleet, as given.
absl::Status SettingsFromFlags(const FlagValues& flags,
                               v1::FleetSettings* settings) {
  const std::pair<const char*, void (v1::FleetSettings::*)(uint32_t)> counts[] =
      {{"clusters-per-segment", &v1::FleetSettings::set_clusters_per_segment},
       {"max-traces-per-cluster",
        &v1::FleetSettings::set_max_traces_per_cluster},
       {"max-clusters", &v1::FleetSettings::set_max_clusters}};
  for (const auto& [name, set] : counts) {
    if (!flags.Has(name)) continue;
    absl::StatusOr<uint64_t> value = flags.RequiredUint(name, UINT32_MAX);
    if (!value.ok()) return value.status();
    (settings->*set)(static_cast<uint32_t>(*value));
  }
  for (const char* name : {"max-age-seconds", "max-traces-per-robot"}) {
    if (!flags.Has(name)) continue;
    absl::StatusOr<uint64_t> value = flags.RequiredUint(name);
    if (!value.ok()) return value.status();
    if (absl::string_view(name) == "max-age-seconds") {
      settings->set_max_age_seconds(*value);
    } else {
      settings->set_max_traces_per_robot(*value);
    }
  }
  if (flags.Has("replay-decay")) {
    absl::StatusOr<double> decay = flags.RequiredDouble("replay-decay");
    if (!decay.ok()) return decay.status();
    settings->set_replay_decay(*decay);
  }
  if (flags.Has("refresh-pairs")) {
    absl::StatusOr<double> radius = flags.RequiredDouble("refresh-pairs");
    if (!radius.ok()) return radius.status();
    settings->set_refresh_pair_radius(*radius);
  }
  if (flags.Has("refresh-uniform")) {
    const std::string value = flags.StringOr("refresh-uniform", "");
    if (value != "true" && value != "false") {
      return absl::InvalidArgumentError(absl::StrCat(
          "--refresh-uniform: \"", value, "\" is not true or false"));
    }
    settings->set_refresh_uniform(value == "true");
  }
  if (flags.Has("forgetting")) {
    const std::string rule = flags.StringOr("forgetting", "");
    if (rule != "merge" && rule != "drop") {
      return absl::InvalidArgumentError(
          absl::StrCat("--forgetting: \"", rule, "\" is not merge or drop"));
    }
    settings->set_forgetting(rule == "merge" ? v1::FORGETTING_RULE_MERGE
                                             : v1::FORGETTING_RULE_DROP);
  }
  return absl::OkStatus();
}

}  // namespace

int RunCreateFleet(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<uint64_t> dimension = flags.RequiredUint("dim", 65'536);
  if (!dimension.ok()) return UsageError(invocation, dimension.status());
  v1::CreateFleetRequest request;
  request.set_fleet_id(*fleet);
  v1::FleetSettings* settings = request.mutable_settings();
  settings->set_code_dimension(static_cast<uint32_t>(*dimension));
  settings->set_encoder_version(flags.StringOr("encoder", ""));
  settings->set_place_unit(flags.StringOr("place-unit", ""));
  if (absl::Status status = SettingsFromFlags(flags, settings); !status.ok()) {
    return UsageError(invocation, status);
  }
  if (flags.Has("index")) {
    v1::IndexKind kind = v1::INDEX_KIND_UNSPECIFIED;
    const std::string name = absl::AsciiStrToUpper(
        absl::StrCat("index_kind_", flags.StringOr("index", "")));
    if (!v1::IndexKind_Parse(name, &kind) ||
        kind == v1::INDEX_KIND_UNSPECIFIED) {
      return UsageError(invocation,
                        absl::InvalidArgumentError(absl::StrCat(
                            "--index: \"", flags.StringOr("index", ""),
                            "\" is not exact, hnsw or auto")));
    }
    settings->set_index(kind);
  }
  for (const auto& [name, set] :
       {std::pair{"hnsw-m", &v1::FleetSettings::set_hnsw_m},
        std::pair{"hnsw-ef", &v1::FleetSettings::set_hnsw_ef_search}}) {
    if (!flags.Has(name)) continue;
    absl::StatusOr<uint64_t> value = flags.RequiredUint(name, 10'000);
    if (!value.ok()) return UsageError(invocation, value.status());
    (settings->*set)(static_cast<uint32_t>(*value));
  }
  if (flags.Has("hnsw-codes")) {
    v1::HnswCodes codes = v1::HNSW_CODES_UNSPECIFIED;
    const std::string name = absl::AsciiStrToUpper(
        absl::StrCat("hnsw_codes_", flags.StringOr("hnsw-codes", "")));
    if (!v1::HnswCodes_Parse(name, &codes) ||
        codes == v1::HNSW_CODES_UNSPECIFIED) {
      return UsageError(
          invocation, absl::InvalidArgumentError(absl::StrCat(
                          "--hnsw-codes: \"", flags.StringOr("hnsw-codes", ""),
                          "\" is not int8 or float")));
    }
    settings->set_hnsw_codes(codes);
  }
  absl::StatusOr<v1::CreateFleetResponse> response =
      Connect(invocation)->CreateFleet(request);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(
      invocation, *response,
      [](const v1::CreateFleetResponse& made, std::ostream& out) {
        PrintFleetSettings(made.settings(), out);
      });
}

int RunFleet(const Invocation& invocation) {
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<v1::GetFleetResponse> response =
      Connect(invocation)->GetFleet(*fleet);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(
      invocation, *response,
      [](const v1::GetFleetResponse& got, std::ostream& out) {
        const v1::FleetSummary& summary = got.fleet();
        out << "fleet " << summary.fleet_id() << ": " << summary.traces()
            << " traces, " << summary.pending_traces() << " pending, "
            << summary.clusters() << " clusters, " << summary.robots()
            << " robots; settings "
            << (summary.own_settings() ? "its own" : "the server's") << "\n";
        PrintFleetSettings(summary.settings(), out);
      });
}

int RunUpdateFleet(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  v1::UpdateFleetRequest request;
  request.set_fleet_id(*fleet);
  if (absl::Status status =
          SettingsFromFlags(flags, request.mutable_settings());
      !status.ok()) {
    return UsageError(invocation, status);
  }
  absl::StatusOr<v1::UpdateFleetResponse> response =
      Connect(invocation)->UpdateFleet(request);
  if (!response.ok()) return ServerError(invocation, response.status());
  return PrintResponse(
      invocation, *response,
      [](const v1::UpdateFleetResponse& updated, std::ostream& out) {
        PrintFleetSettings(updated.settings(), out);
      });
}

std::unique_ptr<client::Client> Connect(const Invocation& invocation) {
  return client::Client::Create(invocation.client_options);
}

}  // namespace fleetmem::cli
