#include "services/transport/memory_service.h"

#include <utility>
#include <vector>

#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_reactor.h"
#include "services/transport/watch_reactor.h"

namespace fleetmem::transport {

MemoryServiceImpl::MemoryServiceImpl(engine::MemoryEngine* engine,
                                     WorkQueue* work)
    : state_(engine, work) {}

void MemoryServiceImpl::Shutdown() { state_.Shutdown(); }

grpc::ServerUnaryReactor* MemoryServiceImpl::RunUnary(
    grpc::CallbackServerContext* context,
    absl::AnyInvocable<absl::Status() &&> work) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  if (state_.shutting_down()) {
    reactor->Finish(ShuttingDownStatus());
    return reactor;
  }
  bool queued = state_.work().TrySubmit(
      [context, reactor, work = std::move(work)]() mutable {
        grpc::Status live = CheckCallLive(*context);
        if (!live.ok()) {
          reactor->Finish(live);
          return;
        }
        reactor->Finish(ToGrpcStatus(std::move(work)()));
      });
  if (!queued) reactor->Finish(ServerBusyStatus());
  return reactor;
}

grpc::ServerReadReactor<v1::UploadTracesRequest>*
MemoryServiceImpl::UploadTraces(grpc::CallbackServerContext* context,
                                v1::UploadTracesResponse* response) {
  return new UploadReactor(&state_, context, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::Consolidate(
    grpc::CallbackServerContext* context, const v1::ConsolidateRequest* request,
    v1::ConsolidateResponse* response) {
  return RunUnary(context, [this, request, response]() -> absl::Status {
    absl::StatusOr<engine::ConsolidateResult> result =
        state_.engine().Consolidate(request->fleet_id());
    if (!result.ok()) return result.status();
    ConsolidateResultToProto(*result, response);
    return absl::OkStatus();
  });
}

grpc::ServerUnaryReactor* MemoryServiceImpl::SampleReplay(
    grpc::CallbackServerContext* context,
    const v1::SampleReplayRequest* request,
    v1::SampleReplayResponse* response) {
  return RunUnary(context, [this, request, response]() -> absl::Status {
    absl::StatusOr<std::vector<core::MemoryTrace>> traces =
        state_.engine().SampleReplay(request->fleet_id(), request->robot_id(),
                                     request->count());
    if (!traces.ok()) return traces.status();
    SampledTracesToProto(*traces, response);
    return absl::OkStatus();
  });
}

grpc::ServerUnaryReactor* MemoryServiceImpl::QueryPlace(
    grpc::CallbackServerContext* context, const v1::QueryPlaceRequest* request,
    v1::QueryPlaceResponse* response) {
  return RunUnary(context, [this, request, response]() -> absl::Status {
    absl::StatusOr<std::vector<engine::PlaceMatch>> matches =
        state_.engine().QueryPlace(request->fleet_id(),
                                   QueryFromProto(*request));
    if (!matches.ok()) return matches.status();
    MatchesToProto(*matches, response);
    return absl::OkStatus();
  });
}

grpc::ServerWriteReactor<v1::MemoryEvent>* MemoryServiceImpl::WatchMemory(
    grpc::CallbackServerContext* context,
    const v1::WatchMemoryRequest* request) {
  return new WatchReactor(&state_, *request);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::GetStats(
    grpc::CallbackServerContext* context, const v1::GetStatsRequest* request,
    v1::GetStatsResponse* response) {
  return RunUnary(context, [this, request, response]() -> absl::Status {
    absl::StatusOr<engine::FleetStats> stats =
        state_.engine().GetStats(request->fleet_id());
    if (!stats.ok()) return stats.status();
    StatsToProto(*stats, response);
    return absl::OkStatus();
  });
}

}  // namespace fleetmem::transport
