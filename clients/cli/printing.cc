#include "clients/cli/printing.h"

#include <algorithm>
#include <map>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "google/protobuf/util/json_util.h"

namespace fleetmem::cli {
namespace {

std::string Metres(double value) { return absl::StrFormat("%.2f", value); }
std::string Fixed(double value) { return absl::StrFormat("%.4f", value); }
std::string Or(const std::string& text, const char* fallback) {
  return text.empty() ? fallback : text;
}

// Two-column table of labelled values.
void PrintPairs(std::vector<std::pair<std::string, std::string>> pairs,
                std::ostream& out) {
  Table table;
  for (auto& [label, value] : pairs) {
    table.AddRow({std::move(label), std::move(value)});
  }
  table.Print(out);
}

}  // namespace

void Table::AddRow(std::vector<std::string> cells) {
  rows_.push_back(std::move(cells));
}

void Table::Print(std::ostream& out) const {
  std::vector<size_t> widths;
  for (const auto& row : rows_) {
    widths.resize(std::max(widths.size(), row.size()), 0);
    for (size_t i = 0; i < row.size(); ++i) {
      widths[i] = std::max(widths[i], row[i].size());
    }
  }
  for (const auto& row : rows_) {
    std::string line;
    for (size_t i = 0; i < row.size(); ++i) {
      absl::StrAppend(&line, row[i]);
      if (i + 1 < row.size()) {
        line.append(widths[i] - row[i].size() + 2, ' ');
      }
    }
    out << line << '\n';
  }
}

void PrintJson(const google::protobuf::Message& message, bool pretty,
               std::ostream& out) {
  google::protobuf::util::JsonPrintOptions options;
  options.add_whitespace = pretty;
  options.always_print_primitive_fields = true;
  std::string json;
  // Printing a valid message cannot fail (no Any fields in the API).
  (void)google::protobuf::util::MessageToJsonString(message, &json, options);
  out << json;
  if (json.empty() || json.back() != '\n') out << '\n';
}

void PrintUpload(const v1::UploadTracesResponse& response, std::ostream& out) {
  PrintPairs({{"accepted", absl::StrCat(response.accepted())},
              {"duplicates", absl::StrCat(response.duplicates())},
              {"consolidations", absl::StrCat(response.consolidations())}},
             out);
}

void PrintFleetSettings(const v1::FleetSettings& settings, std::ostream& out) {
  PrintPairs(
      {{"code dimension", absl::StrCat(settings.code_dimension())},
       {"encoder version", Or(settings.encoder_version(), "-")},
       {"place unit", Or(settings.place_unit(), "-")},
       {"clusters per segment (K)",
        absl::StrCat(settings.clusters_per_segment())},
       {"traces per cluster (N_max)",
        absl::StrCat(settings.max_traces_per_cluster())},
       {"clusters (K_max)", absl::StrCat(settings.max_clusters())},
       {"replay decay (gamma)", absl::StrCat(settings.replay_decay())},
       {"forgetting",
        settings.forgetting() == v1::FORGETTING_RULE_DROP ? "drop" : "merge"},
       {"refresh",
        absl::StrCat(settings.refresh_uniform() ? "uniform" : "gamma^n R",
                     settings.refresh_pair_radius() > 0.0
                         ? absl::StrCat(", pairs within ",
                                        settings.refresh_pair_radius())
                         : std::string())},
       {"max age", settings.max_age_seconds() == 0
                       ? "-"
                       : absl::StrCat(settings.max_age_seconds(), " s")},
       {"max traces per robot",
        settings.max_traces_per_robot() == 0
            ? "-"
            : absl::StrCat(settings.max_traces_per_robot())},
       {"index",
        settings.index() == v1::INDEX_KIND_UNSPECIFIED
            ? std::string("the server's")
            : absl::StrCat(absl::AsciiStrToLower(
                               v1::IndexKind_Name(settings.index()).substr(11)),
                           settings.hnsw_m()
                               ? absl::StrCat(" M ", settings.hnsw_m())
                               : std::string(),
                           settings.hnsw_ef_search()
                               ? absl::StrCat(" ef ", settings.hnsw_ef_search())
                               : std::string())},
       {"graph codes",
        settings.hnsw_codes() == v1::HNSW_CODES_UNSPECIFIED
            ? std::string("the server's")
            : absl::AsciiStrToLower(
                  v1::HnswCodes_Name(settings.hnsw_codes()).substr(11))}},
      out);
}

void PrintDelete(const v1::DeleteTracesResponse& response, std::ostream& out) {
  PrintPairs({{"deleted traces", absl::StrCat(response.deleted())},
              {"of them pending", absl::StrCat(response.pending_deleted())},
              {"clusters changed", absl::StrCat(response.clusters_changed())},
              {"clusters removed", absl::StrCat(response.clusters_removed())},
              {"traces left", absl::StrCat(response.traces())}},
             out);
}

void PrintRewards(const v1::UpdateRewardsResponse& response,
                  std::ostream& out) {
  PrintPairs({{"updated", absl::StrCat(response.updated())},
              {"not held", absl::StrCat(response.not_held_size())}},
             out);
  for (const v1::TraceKey& key : response.not_held()) {
    out << "  not held: " << key.robot_id() << " " << key.seq() << "\n";
  }
}

void PrintConsolidate(const v1::ConsolidateResponse& response,
                      std::ostream& out) {
  PrintPairs(
      {{"consolidated traces", absl::StrCat(response.consolidated_traces())},
       {"downsampled traces", absl::StrCat(response.downsampled_traces())},
       {"clusters added", absl::StrCat(response.clusters_added())},
       {"clusters forgotten", absl::StrCat(response.clusters_forgotten())},
       {"clusters", absl::StrCat(response.clusters())},
       {"traces", absl::StrCat(response.traces())}},
      out);
}

void PrintStats(const v1::GetStatsResponse& stats, std::ostream& out) {
  // One table, so that every value starts in one column.
  std::vector<std::pair<std::string, std::string>> pairs = {
      {"traces", absl::StrCat(stats.traces())},
      {"pending traces", absl::StrCat(stats.pending_traces())},
      {"clusters",
       absl::StrCat(stats.clusters(), " (max ", stats.max_clusters(), ")")},
      {"traces per cluster",
       absl::StrCat("max ", stats.max_traces_per_cluster())},
      {"code dimension", absl::StrCat(stats.code_dimension())},
      {"encoder version", Or(stats.encoder_version(), "-")},
      {"consolidations", absl::StrCat(stats.consolidations())},
      {"clusters forgotten", absl::StrCat(stats.clusters_forgotten())},
      {"last event id", absl::StrCat(stats.last_event_id())}};
  if (stats.acknowledged_through() > 0) {
    // The write path: uploads acknowledged and not applied yet.
    pairs.emplace_back(
        "log applied through",
        absl::StrCat(stats.applied_through(), " of ",
                     stats.acknowledged_through(), " acknowledged"));
    pairs.emplace_back(
        "write backlog",
        absl::StrFormat("%d traces in %d uploads, oldest %.1f s",
                        stats.backlog_traces(), stats.backlog_entries(),
                        stats.backlog_age_seconds()));
  }
  if (!stats.apply_error().empty()) {
    pairs.emplace_back("apply error", stats.apply_error());
  }
  PrintPairs(std::move(pairs), out);
  if (!stats.robots().empty()) {
    out << '\n';
    Table robots;
    robots.AddRow(
        {"ROBOT", "TRACES", "PENDING", "MAX SEQ", "RECEIVED", "SAMPLED"});
    for (const v1::RobotStats& robot : stats.robots()) {
      robots.AddRow(
          {robot.robot_id(), absl::StrCat(robot.traces()),
           absl::StrCat(robot.pending_traces()), absl::StrCat(robot.max_seq()),
           absl::StrCat(robot.received()), absl::StrCat(robot.replayed())});
    }
    robots.Print(out);
  }
  if (!stats.domains().empty()) {
    out << '\n';
    Table domains;
    domains.AddRow({"DOMAIN", "TRACES", "PENDING"});
    for (const v1::DomainStats& domain : stats.domains()) {
      domains.AddRow({Or(domain.domain(), "-"), absl::StrCat(domain.traces()),
                      absl::StrCat(domain.pending_traces())});
    }
    domains.Print(out);
  }
}

void PrintMatches(std::span<const v1::PlaceMatch> matches, std::ostream& out) {
  if (matches.empty()) {
    out << "no matches\n";
    return;
  }
  Table table;
  table.AddRow({"#", "DISTANCE", "ROBOT", "SEQ", "DOMAIN", "X", "Y", "Z",
                "CLUSTER", "REWARD"});
  int rank = 0;
  for (const v1::PlaceMatch& match : matches) {
    const v1::MemoryTrace& trace = match.trace();
    table.AddRow({absl::StrCat(++rank), Fixed(match.distance()),
                  trace.robot_id(), absl::StrCat(trace.seq()),
                  Or(trace.domain(), "-"), Metres(trace.pose().x()),
                  Metres(trace.pose().y()), Metres(trace.pose().z()),
                  absl::StrCat(trace.cluster_id()), Fixed(trace.reward())});
  }
  table.Print(out);
}

void PrintTraces(std::span<const v1::MemoryTrace> traces, std::ostream& out) {
  if (traces.empty()) {
    out << "no traces\n";
    return;
  }
  Table table;
  table.AddRow({"ROBOT", "SEQ", "DOMAIN", "X", "Y", "Z", "REWARD", "REPLAYS",
                "CLUSTER"});
  for (const v1::MemoryTrace& trace : traces) {
    table.AddRow({trace.robot_id(), absl::StrCat(trace.seq()),
                  Or(trace.domain(), "-"), Metres(trace.pose().x()),
                  Metres(trace.pose().y()), Metres(trace.pose().z()),
                  Fixed(trace.reward()), absl::StrCat(trace.replay_count()),
                  absl::StrCat(trace.cluster_id())});
  }
  table.Print(out);
}

void PrintEvent(const v1::MemoryEvent& event, std::ostream& out) {
  out << absl::StrFormat(
      "%d %s cluster=%d traces=%d robot=%s domain=%s "
      "at=(%.2f, %.2f, %.2f) mean_reward=%.4f",
      event.id(), v1::MemoryEvent::Type_Name(event.type()), event.cluster_id(),
      event.trace_count(), Or(event.robot_id(), "-"), Or(event.domain(), "-"),
      event.centroid_pose().x(), event.centroid_pose().y(),
      event.centroid_pose().z(), event.mean_reward());
  if (event.type() == v1::MemoryEvent::CLUSTER_MERGED) {
    out << absl::StrFormat(" merged_into=%d traces_dropped=%d",
                           event.merged_into(), event.traces_dropped());
  }
  if (event.type() == v1::MemoryEvent::TRACES_DELETED) {
    out << absl::StrFormat(" traces_deleted=%d", event.traces_dropped());
  }
  out << std::endl;  // Flushed: a watch is often piped.
}

void PrintFleets(const v1::ListFleetsResponse& fleets, std::ostream& out) {
  if (fleets.fleets().empty()) {
    out << "no fleets\n";
    return;
  }
  Table table;
  table.AddRow({"fleet", "traces", "pending", "clusters", "robots", "dim",
                "encoder", "last event"});
  for (const v1::FleetSummary& fleet : fleets.fleets()) {
    table.AddRow({fleet.fleet_id(), absl::StrCat(fleet.traces()),
                  absl::StrCat(fleet.pending_traces()),
                  absl::StrCat(fleet.clusters()), absl::StrCat(fleet.robots()),
                  absl::StrCat(fleet.code_dimension()), fleet.encoder_version(),
                  absl::StrCat(fleet.last_event_id())});
  }
  table.Print(out);
}

namespace {

// "robot-1:12 robot-2:3", by name.
std::string Counts(const google::protobuf::Map<std::string, uint32_t>& counts) {
  std::map<std::string, uint32_t> sorted(counts.begin(), counts.end());
  std::string text;
  for (const auto& [name, count] : sorted) {
    absl::StrAppend(&text, text.empty() ? "" : " ",
                    name.empty() ? "(none)" : name, ":", count);
  }
  return text;
}

}  // namespace

void PrintClusters(const v1::ListClustersResponse& clusters,
                   std::ostream& out) {
  if (clusters.clusters().empty()) {
    out << "no clusters yet\n";
    return;
  }
  Table table;
  table.AddRow(
      {"cluster", "traces", "x", "y", "mean reward", "robots", "domains"});
  for (const v1::ClusterSummary& cluster : clusters.clusters()) {
    table.AddRow({absl::StrCat(cluster.cluster_id()),
                  absl::StrCat(cluster.trace_count()),
                  absl::StrFormat("%.1f", cluster.centroid_pose().x()),
                  absl::StrFormat("%.1f", cluster.centroid_pose().y()),
                  absl::StrFormat("%.3f", cluster.mean_reward()),
                  Counts(cluster.robots()), Counts(cluster.domains())});
  }
  table.Print(out);
}

void PrintSnapshot(const v1::CreateSnapshotResponse& snapshot,
                   std::ostream& out) {
  out << "snapshot of " << snapshot.fleets() << " fleet(s) written to "
      << snapshot.path()
      << "\nrestore: fleetmem-server --data-dir NEW_DIR --restore-from "
      << snapshot.path() << "\n";
}

}  // namespace fleetmem::cli
