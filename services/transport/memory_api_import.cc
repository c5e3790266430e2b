// ImportTraces: a bulk import's chunk as uploads, the fleet's graph
// deferred until the last call builds it (memory_api.h).
#include <algorithm>
#include <span>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "services/core/validation.h"
#include "services/transport/memory_api.h"
#include "services/transport/proto_convert.h"

namespace fleetmem::transport {
namespace {

// `traces` as uploads of a segment each (at most max_traces_per_upload): a
// robot's rows are consolidated in the segments its uploads would have
// made, not in batches as large as the chunk (whose clusters would be
// downsampled where its robot's segments' are not).
std::vector<std::span<const core::MemoryTrace>> SegmentsOf(
    std::span<const core::MemoryTrace> traces,
    const engine::EngineOptions& options) {
  const size_t per_message = std::max<size_t>(
      1, std::min(options.max_traces_per_upload, options.segment_size));
  std::vector<std::span<const core::MemoryTrace>> messages;
  for (size_t first = 0; first < traces.size(); first += per_message) {
    messages.push_back(
        traces.subspan(first, std::min(per_message, traces.size() - first)));
  }
  return messages;
}

}  // namespace

absl::Status MemoryApi::ImportTraces(const auth::Principal& caller,
                                     const v1::ImportTracesRequest& request,
                                     v1::ImportTracesResponse* response) {
  const std::string& fleet_id = request.fleet_id();
  absl::Status status = core::ValidateId("fleet_id", fleet_id);
  if (status.ok()) {
    status = AuthorizeCall("ImportTraces", caller, request, fleet_id);
  }
  if (!status.ok()) return status;
  if (request.traces().count() > kMaxImportRows) {
    return absl::InvalidArgumentError(absl::StrCat(
        "traces.count: ", request.traces().count(), " rows; at most ",
        kMaxImportRows, " a call (send the rest in further calls)"));
  }
  absl::StatusOr<std::vector<core::MemoryTrace>> traces =
      ImportedTracesFromColumns(request.traces());
  if (!traces.ok()) return traces.status();
  const bool exists = engine_->CheckFleetExists(fleet_id).ok();
  if (exists && !request.resume()) {
    status = CheckNothingHeld(fleet_id);
    if (!status.ok()) return status;
  }
  const std::vector<std::span<const core::MemoryTrace>> messages =
      SegmentsOf(*traces, engine_->options());
  std::span<const std::span<const core::MemoryTrace>> rest(messages);
  UploadOptions options;
  options.wait_applied = request.finish();
  size_t sent = 0;
  if (!exists && !rest.empty()) {
    // The first message makes the fleet, applied before the rest, so that
    // its index is deferred before their codes reach it.
    UploadOptions first = options;
    first.wait_applied = true;
    status = UploadImported(fleet_id, rest.first(1), first, &sent, response);
    if (!status.ok()) return status;
    rest = rest.subspan(1);
  }
  // Best effort: a fleet this engine does not hold (another replica
  // applies it) is indexed as it goes.
  (void)engine_->DeferIndexing(fleet_id, absl::Now() + kImportIdle);
  status = UploadImported(fleet_id, rest, options, &sent, response);
  if (!status.ok()) return status;
  if (!request.finish()) {  // the deferral from this call's end
    (void)engine_->DeferIndexing(fleet_id, absl::Now() + kImportIdle);
    return absl::OkStatus();
  }
  return BuildImportedGraph(fleet_id, response);
}

absl::Status MemoryApi::CheckNothingHeld(const std::string& fleet_id) {
  if (engine_->IndexingDeferred(fleet_id)) return absl::OkStatus();
  absl::StatusOr<engine::FleetStats> stats = engine_->GetStats(fleet_id);
  const uint64_t held =
      (stats.ok() ? stats->traces + stats->pending_traces : 0) +
      memory_->Backlog(fleet_id).traces;
  if (held == 0) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      "fleet \"", fleet_id, "\" holds ", held,
      " traces and no import into it is under way: an import fills a "
      "fleet that holds none (set resume to go on with an interrupted "
      "one); nothing was imported"));
}

absl::Status MemoryApi::UploadImported(
    const std::string& fleet_id,
    std::span<const std::span<const core::MemoryTrace>> messages,
    const UploadOptions& options, size_t* sent,
    v1::ImportTracesResponse* response) {
  std::vector<absl::StatusOr<Uploaded>> results =
      memory_->UploadMany(fleet_id, messages, options);
  for (size_t i = 0; i < results.size(); ++i) {
    if (!results[i].ok()) {
      return absl::Status(
          results[i].status().code(),
          absl::StrCat("rows ", *sent + 1, "..", *sent + messages[i].size(),
                       " of this call: ", results[i].status().message(),
                       "; the ", *sent,
                       " rows before them are stored (durable; duplicates "
                       "when sent again), none after them"));
    }
    response->set_accepted(response->accepted() + results[i]->result.accepted);
    response->set_duplicates(response->duplicates() +
                             results[i]->result.duplicates);
    *sent += messages[i].size();
  }
  return absl::OkStatus();
}

absl::Status MemoryApi::BuildImportedGraph(const std::string& fleet_id,
                                           v1::ImportTracesResponse* response) {
  if (!engine_->CheckFleetExists(fleet_id).ok()) {
    return absl::FailedPreconditionError(absl::StrCat(
        "fleet \"", fleet_id,
        "\": nothing was imported into it, so there is no graph to build"));
  }
  const absl::Time started = absl::Now();
  const absl::Status status = engine_->IndexDeferred(fleet_id);
  response->set_index_seconds(absl::ToDoubleSeconds(absl::Now() - started));
  absl::StatusOr<engine::FleetStats> stats = engine_->GetStats(fleet_id);
  if (stats.ok()) {
    response->set_fleet_traces(stats->traces + stats->pending_traces);
    response->set_unindexed_codes(stats->unindexed_codes);
  }
  if (!status.ok()) {
    return absl::Status(
        status.code(),
        absl::StrCat("every row of the import is stored, but building the "
                     "place graph stopped: ",
                     status.message(),
                     " (the codes left out are found by an exact scan)"));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::transport
