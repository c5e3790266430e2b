// Output of the `fleetmem` tool: human-readable tables, or with --json one
// compact protobuf JSON document per line (every field printed, also zeros;
// 64-bit integers are JSON strings, as the protobuf JSON mapping says).
#ifndef FLEETMEM_CLIENTS_CLI_PRINTING_H_
#define FLEETMEM_CLIENTS_CLI_PRINTING_H_

#include <ostream>
#include <span>
#include <string>
#include <vector>

#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/message.h"

namespace fleetmem::cli {

// Aligned columns; the first row is the header.
class Table {
 public:
  void AddRow(std::vector<std::string> cells);
  void Print(std::ostream& out) const;

 private:
  std::vector<std::vector<std::string>> rows_;
};

// `message` as JSON: indented when `pretty`, else on one line. Ends with a
// newline.
void PrintJson(const google::protobuf::Message& message, bool pretty,
               std::ostream& out);

void PrintUpload(const v1::UploadTracesResponse& response, std::ostream& out);
void PrintFleetSettings(const v1::FleetSettings& settings, std::ostream& out);
void PrintDelete(const v1::DeleteTracesResponse& response, std::ostream& out);
void PrintRewards(const v1::UpdateRewardsResponse& response, std::ostream& out);
void PrintConsolidate(const v1::ConsolidateResponse& response,
                      std::ostream& out);
void PrintStats(const v1::GetStatsResponse& stats, std::ostream& out);
void PrintFleets(const v1::ListFleetsResponse& fleets, std::ostream& out);
void PrintClusters(const v1::ListClustersResponse& clusters, std::ostream& out);
void PrintSnapshot(const v1::CreateSnapshotResponse& snapshot,
                   std::ostream& out);
void PrintMatches(std::span<const v1::PlaceMatch> matches, std::ostream& out);
void PrintTraces(std::span<const v1::MemoryTrace> traces, std::ostream& out);
// One line per event (a watch cannot align columns ahead of time).
void PrintEvent(const v1::MemoryEvent& event, std::ostream& out);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_PRINTING_H_
