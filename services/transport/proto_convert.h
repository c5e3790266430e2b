// Conversions between the fleetmem.v1 API messages and the engine's domain
// types. Pure functions; no validation (the engine validates domain values).
#ifndef FLEETMEM_SERVICES_TRANSPORT_PROTO_CONVERT_H_
#define FLEETMEM_SERVICES_TRANSPORT_PROTO_CONVERT_H_

#include <span>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/repeated_ptr_field.h"
#include "proto/convert/trace_convert.h"
#include "services/core/types.h"
#include "services/engine/memory_engine.h"
#include "services/engine/write_path.h"

namespace fleetmem::transport {

// Traces and places: shared with the robot (proto/convert).
using api::PlaceFromProto;
using api::PlaceToProto;
using api::TraceFromProto;
using api::TraceToProto;

// The traces of an upload message. replay_count and cluster_id are set by
// the server, so they are cleared here ("ignored on upload").
std::vector<core::MemoryTrace> UploadedTracesFromProto(
    const google::protobuf::RepeatedPtrField<v1::MemoryTrace>& traces);

// CLUSTER_ADDED / CLUSTER_FORGOTTEN / CLUSTER_MERGED / TRACES_DELETED.
void EventToProto(const core::MemoryEvent& event, v1::MemoryEvent* out);

engine::PlaceQuery QueryFromProto(const v1::QueryPlaceRequest& request);

// Adds `result` to the counters of `out` (an upload stream sums its
// messages).
void AddUploadResult(const engine::UploadResult& result,
                     v1::UploadTracesResponse* out);
void ConsolidateResultToProto(const engine::ConsolidateResult& result,
                              v1::ConsolidateResponse* out);
void SampledTracesToProto(std::span<const core::MemoryTrace> traces,
                          v1::SampleReplayResponse* out);
// The same traces as columns (SampleReplayRequest.columnar): the codes in
// one float32 block, every other field a packed array, row i trace i.
void TraceColumnsToProto(std::span<const core::MemoryTrace> traces,
                         v1::TraceColumns* out);
// The rows of an ImportTraces chunk as an upload's traces (replay_count and
// cluster_id 0). INVALID_ARGUMENT naming the column that does not fit
// `count` rows (codes: count x code_dimension floats; places: 4 a row;
// the optional columns: empty or one a row), or replay_counts /
// cluster_ids given (they are not imported). The values are checked later,
// as an upload's.
absl::StatusOr<std::vector<core::MemoryTrace>> ImportedTracesFromColumns(
    const v1::TraceColumns& columns);
void MatchesToProto(std::span<const engine::PlaceMatch> matches,
                    v1::QueryPlaceResponse* out);
void StatsToProto(const engine::FleetStats& stats, v1::GetStatsResponse* out);
void BacklogToProto(const engine::Backlog& backlog, v1::GetStatsResponse* out);
void FleetSummaryToProto(std::string_view fleet_id,
                         const engine::FleetStats& stats,
                         v1::FleetSummary* out);
void ClustersToProto(const engine::ClusterListing& listing,
                     v1::ListClustersResponse* out);
// A CreateFleet's settings: unset fields take `defaults` (the server's).
// A fleet's index settings, and their kind in the API.
engine::IndexSettings IndexFromProto(const v1::FleetSettings& settings);
v1::IndexKind IndexKindToProto(engine::IndexSettings::Kind kind);
engine::CreateFleetRecord CreateFleetFromProto(
    const v1::FleetSettings& settings, const core::MemoryOptions& defaults);
// An UpdateFleet's change of `current`: FAILED_PRECONDITION naming the
// field when one fixed at creation is set to another value.
absl::StatusOr<engine::FleetSettingsUpdate> FleetUpdateFromProto(
    const v1::FleetSettings& settings, const engine::FleetInfo& current);
// Every field of `info`'s settings.
void FleetSettingsToProto(const engine::FleetInfo& info,
                          v1::FleetSettings* out);

void DeleteResultToProto(const engine::DeleteResult& result,
                         v1::DeleteTracesResponse* out);
void RewardsResultToProto(const engine::RewardsResult& result,
                          v1::UpdateRewardsResponse* out);
std::vector<core::TraceKey> KeysFromProto(
    const google::protobuf::RepeatedPtrField<v1::TraceKey>& keys);
void TraceLookupToProto(const engine::TraceLookup& lookup,
                        v1::GetTracesResponse* out);

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_PROTO_CONVERT_H_
