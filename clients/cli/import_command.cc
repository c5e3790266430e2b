// `fleetmem import`: a recorded fleet's .npy arrays (the export's format)
// into a fleet, a chunk per ImportTraces call, the graph built at the end.
#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_split.h"
#include "clients/cli/commands.h"
#include "clients/cli/npy_reader.h"

namespace fleetmem::cli {
namespace {

// Bytes of codes one call carries by default: within the server's default
// max_receive_message_bytes (16 MiB) with room for the other columns.
constexpr size_t kChunkCodeBytes = size_t{8} << 20;

// metadata.csv (the export's), read a block of rows at a time in step
// with the arrays: its header names the columns; robot_id, seq and reward
// are required, domain, reward_external, reward_internal, timestamp_ns and
// encoder_version used where present, the rest (row, replay_count,
// cluster_id) ignored.
class MetadataReader {
 public:
  static absl::StatusOr<MetadataReader> Open(const std::string& path) {
    MetadataReader reader;
    reader.path_ = path;
    reader.in_ = std::make_unique<std::ifstream>(path);
    std::string header;
    if (!*reader.in_ || !std::getline(*reader.in_, header)) {
      return absl::InvalidArgumentError(absl::StrCat(path, ": no header"));
    }
    const std::vector<std::string> names = absl::StrSplit(header, ',');
    for (size_t i = 0; i < names.size(); ++i) reader.column_[names[i]] = i;
    for (const char* required : {"robot_id", "seq", "reward"}) {
      if (!reader.column_.contains(required)) {
        return absl::InvalidArgumentError(
            absl::StrCat(path, ": no column \"", required, "\""));
      }
    }
    return reader;
  }

  // Appends the next `count` rows to `columns`.
  absl::Status Next(size_t count, v1::TraceColumns* columns) {
    std::string line;
    for (size_t i = 0; i < count; ++i) {
      ++line_number_;
      if (!std::getline(*in_, line)) {
        return absl::InvalidArgumentError(absl::StrCat(
            path_, ": ends at line ", line_number_, " before the arrays do"));
      }
      const std::vector<std::string> fields = absl::StrSplit(line, ',');
      const auto field = [&](const char* name) -> const std::string* {
        const auto found = column_.find(name);
        if (found == column_.end() || found->second >= fields.size()) {
          return nullptr;
        }
        return &fields[found->second];
      };
      const auto bad = [&](const char* name) {
        return absl::InvalidArgumentError(
            absl::StrCat(path_, " line ", line_number_, ": bad ", name, " \"",
                         field(name) == nullptr ? "" : *field(name), "\""));
      };
      uint64_t seq = 0;
      float reward = 0;
      if (field("robot_id") == nullptr) return bad("robot_id");
      if (field("seq") == nullptr || !absl::SimpleAtoi(*field("seq"), &seq)) {
        return bad("seq");
      }
      if (field("reward") == nullptr ||
          !absl::SimpleAtof(*field("reward"), &reward)) {
        return bad("reward");
      }
      columns->add_robot_ids(*field("robot_id"));
      columns->add_seqs(seq);
      columns->add_rewards(reward);
      if (column_.contains("domain")) {
        columns->add_domains(field("domain") ? *field("domain") : "");
      }
      if (column_.contains("encoder_version")) {
        columns->add_encoder_versions(
            field("encoder_version") ? *field("encoder_version") : "");
      }
      for (const char* name : {"reward_external", "reward_internal"}) {
        if (!column_.contains(name)) continue;
        float value = 0;
        if (field(name) == nullptr || !absl::SimpleAtof(*field(name), &value)) {
          return bad(name);
        }
        (std::string_view(name) == "reward_external"
             ? columns->add_rewards_external(value)
             : columns->add_rewards_internal(value));
      }
      if (column_.contains("timestamp_ns")) {
        int64_t ns = 0;
        if (field("timestamp_ns") == nullptr ||
            !absl::SimpleAtoi(*field("timestamp_ns"), &ns)) {
          return bad("timestamp_ns");
        }
        columns->add_timestamps_ns(ns);
      }
    }
    return absl::OkStatus();
  }

 private:
  std::string path_;
  std::unique_ptr<std::ifstream> in_;
  std::map<std::string, size_t> column_;
  size_t line_number_ = 1;
};

// What to import: the arrays opened and checked against each other.
struct Sources {
  NpyReader codes;
  NpyReader places;
  std::optional<NpyReader> rewards;        // without metadata.csv
  std::optional<MetadataReader> metadata;  // with it
};

absl::StatusOr<Sources> OpenSources(const std::filesystem::path& dir) {
  absl::StatusOr<NpyReader> codes = NpyReader::Open(dir / "codes.npy");
  if (!codes.ok()) return codes.status();
  absl::StatusOr<NpyReader> places = NpyReader::Open(dir / "places.npy");
  if (!places.ok()) return places.status();
  Sources sources{*std::move(codes), *std::move(places), std::nullopt,
                  std::nullopt};
  const size_t n = sources.codes.rows();
  if (sources.places.rows() != n || sources.places.cols() < 2 ||
      sources.places.cols() > 4) {
    return absl::InvalidArgumentError(absl::StrFormat(
        "%s is %d x %d; want %d rows of 2 to 4 columns (x, y[, z[, yaw]])",
        sources.places.path(), sources.places.rows(), sources.places.cols(),
        n));
  }
  if (std::filesystem::exists(dir / "metadata.csv")) {
    absl::StatusOr<MetadataReader> metadata =
        MetadataReader::Open(dir / "metadata.csv");
    if (!metadata.ok()) return metadata.status();
    sources.metadata = *std::move(metadata);
  } else if (std::filesystem::exists(dir / "rewards.npy")) {
    absl::StatusOr<NpyReader> rewards = NpyReader::Open(dir / "rewards.npy");
    if (!rewards.ok()) return rewards.status();
    if (rewards->rows() != n || rewards->cols() != 1) {
      return absl::InvalidArgumentError(
          absl::StrFormat("%s is %d x %d; want %d rewards", rewards->path(),
                          rewards->rows(), rewards->cols(), n));
    }
    sources.rewards = *std::move(rewards);
  } else {
    return absl::InvalidArgumentError(absl::StrCat(
        dir.string(),
        " holds neither metadata.csv (robot_id, seq, reward, ...; the "
        "export's) nor rewards.npy (one R per row): the traces' rewards are "
        "needed"));
  }
  return sources;
}

// Rows [first, first + count) as one call's columns.
absl::Status ReadChunk(Sources& sources, size_t first, size_t count,
                       const std::string& robot, const std::string& encoder,
                       v1::TraceColumns* columns) {
  std::vector<float> codes;
  std::vector<double> places;
  absl::Status status = sources.codes.ReadRows(first, count, &codes);
  if (status.ok()) status = sources.places.ReadRows(first, count, &places);
  if (!status.ok()) return status;
  columns->set_count(static_cast<uint32_t>(count));
  columns->set_code_dimension(static_cast<uint32_t>(sources.codes.cols()));
  columns->set_codes(reinterpret_cast<const char*>(codes.data()),
                     codes.size() * sizeof(float));
  const size_t width = sources.places.cols();
  for (size_t i = 0; i < count; ++i) {
    for (size_t c = 0; c < 4; ++c) {
      columns->add_places(c < width ? places[i * width + c] : 0.0);
    }
  }
  if (sources.metadata) {
    status = sources.metadata->Next(count, columns);
  } else {
    std::vector<float> rewards;
    status = sources.rewards->ReadRows(first, count, &rewards);
    for (size_t i = 0; status.ok() && i < count; ++i) {
      columns->add_robot_ids(robot);
      columns->add_seqs(first + i + 1);
      columns->add_rewards(rewards[i]);
    }
  }
  if (!status.ok()) return status;
  if (!encoder.empty()) {
    // Rows without an encoder version get --encoder's.
    if (columns->encoder_versions_size() == 0) {
      for (size_t i = 0; i < count; ++i) columns->add_encoder_versions(encoder);
    } else {
      for (std::string& version : *columns->mutable_encoder_versions()) {
        if (version.empty()) version = encoder;
      }
    }
  }
  return absl::OkStatus();
}

// The import's calls, a chunk of `per_call` rows each, progress on stderr;
// the last call's answer with the calls' counts summed. A server's error
// is printed (with what was stored) and returned; rows that cannot be read
// are returned unprinted with *unreadable set (a usage error).
absl::StatusOr<v1::ImportTracesResponse> SendChunks(
    const Invocation& invocation, client::Client& client, Sources& sources,
    size_t per_call, const std::string& robot, const std::string& encoder,
    const std::function<double()>& seconds, bool* unreadable) {
  const FlagValues& flags = *invocation.flags;
  const std::string fleet = flags.StringOr("fleet", "");
  const size_t rows = sources.codes.rows();
  uint64_t accepted = 0, duplicates = 0;
  v1::ImportTracesResponse last;
  for (size_t first = 0; first < rows || first == 0;) {
    const size_t count = std::min(per_call, rows - first);
    v1::ImportTracesRequest request;
    request.set_fleet_id(fleet);
    request.set_resume(flags.Has("resume"));
    request.set_finish(first + count >= rows);
    absl::Status read = ReadChunk(sources, first, count, robot, encoder,
                                  request.mutable_traces());
    if (!read.ok()) {
      *invocation.err << "\n";
      *unreadable = true;
      return read;
    }
    if (request.finish()) {
      *invocation.err << "\rimported " << first + count << " / " << rows
                      << " rows; building the place graph..." << std::flush;
    }
    absl::StatusOr<v1::ImportTracesResponse> response =
        client.ImportTraces(request);
    if (!response.ok()) {
      *invocation.err << "\nimport stopped: "
                      << (first == 0
                              ? std::string("no earlier call stored a row")
                              : absl::StrCat(
                                    "rows 1..", first,
                                    " are stored (a run with --resume goes "
                                    "on from there; stored rows count as "
                                    "duplicates)"))
                      << "\n";
      ServerError(invocation, response.status());
      return response.status();
    }
    accepted += response->accepted();
    duplicates += response->duplicates();
    last = *response;
    first += count;
    if (!request.finish()) {
      *invocation.err << absl::StrFormat("\rimported %d / %d rows (%.0f/s)",
                                         first, rows, first / seconds())
                      << std::flush;
    }
    if (rows == 0) break;
  }
  last.set_accepted(accepted);
  last.set_duplicates(duplicates);
  return last;
}

}  // namespace

int RunImport(const Invocation& invocation) {
  const FlagValues& flags = *invocation.flags;
  absl::StatusOr<std::string> fleet = flags.Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> from = flags.Required("from");
  if (!from.ok()) return UsageError(invocation, from.status());
  absl::StatusOr<uint64_t> chunk = flags.UintOr("chunk", 0, 100'000);
  if (!chunk.ok()) return UsageError(invocation, chunk.status());
  const std::string robot = flags.StringOr("robot", "import");
  const std::string encoder = flags.StringOr("encoder", "");
  absl::StatusOr<Sources> sources = OpenSources(*from);
  if (!sources.ok()) return UsageError(invocation, sources.status());
  const size_t rows = sources->codes.rows();
  const size_t dimension = sources->codes.cols();
  const size_t per_call =
      *chunk > 0
          ? *chunk
          : std::clamp<size_t>(kChunkCodeBytes / (dimension * 4), 1, 10'000);
  // The last call builds the graph before it answers: minutes at millions.
  client::ClientOptions options = invocation.client_options;
  options.deadline = std::max<std::chrono::milliseconds>(
      options.deadline, std::chrono::hours(24));
  std::unique_ptr<client::Client> client = client::Client::Create(options);
  const auto started = std::chrono::steady_clock::now();
  const auto seconds = [&] {
    return std::chrono::duration<double>(std::chrono::steady_clock::now() -
                                         started)
        .count();
  };
  bool unreadable = false;
  absl::StatusOr<v1::ImportTracesResponse> last =
      SendChunks(invocation, *client, *sources, per_call, robot, encoder,
                 seconds, &unreadable);
  if (!last.ok()) {
    return unreadable ? UsageError(invocation, last.status())
                      : kExitServerError;  // SendChunks said why
  }
  const uint64_t accepted = last->accepted(), duplicates = last->duplicates();
  *invocation.err << "\n";
  if (invocation.json) {
    PrintJson(*last, /*pretty=*/false, *invocation.out);
    return kExitOk;
  }
  *invocation.out << absl::StrFormat(
      "imported %d rows (dimension %d) into fleet %s in %.1f s: %d accepted, "
      "%d duplicates; the fleet holds %d traces, its place graph built in "
      "%.1f s (%d codes outside it)\n",
      rows, dimension, *fleet, seconds(), accepted, duplicates,
      last->fleet_traces(), last->index_seconds(), last->unindexed_codes());
  return kExitOk;
}

}  // namespace fleetmem::cli
