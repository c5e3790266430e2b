#include "services/transport/memory_service.h"

#include <utility>
#include <vector>

#include "services/transport/call_auth.h"
#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_reactor.h"
#include "services/transport/watch_reactor.h"

namespace fleetmem::transport {

MemoryServiceImpl::MemoryServiceImpl(engine::MemoryEngine* engine,
                                     WorkQueue* work,
                                     const auth::Authenticator* authenticator,
                                     ServiceOptions options)
    : state_(engine, work, authenticator, options) {}

void MemoryServiceImpl::Shutdown() { state_.Shutdown(); }

bool MemoryServiceImpl::WaitIdle(absl::Time deadline) {
  return state_.WaitIdle(deadline);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::RunUnary(
    grpc::CallbackServerContext* context, auth::Action action,
    std::string fleet_id, std::string robot_id,
    absl::AnyInvocable<absl::Status() &&> work) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  if (state_.shutting_down()) {
    reactor->Finish(ShuttingDownStatus());
    return reactor;
  }
  state_.BeginWork();
  bool queued = state_.work().TrySubmit(
      [this, context, reactor, action, fleet_id = std::move(fleet_id),
       robot_id = std::move(robot_id), work = std::move(work)]() mutable {
        reactor->Finish([&] {
          grpc::Status live = CheckCallLive(*context);
          if (!live.ok()) return live;
          absl::StatusOr<auth::Principal> allowed = AuthorizeCall(
              state_.authenticator(), *context, action, fleet_id, robot_id);
          if (!allowed.ok()) return ToGrpcStatus(allowed.status());
          return ToGrpcStatus(std::move(work)());
        }());
        state_.EndWork();
      });
  if (!queued) {
    state_.EndWork();
    reactor->Finish(ServerBusyStatus());
  }
  return reactor;
}

grpc::ServerReadReactor<grpc::ByteBuffer>* MemoryServiceImpl::UploadTraces(
    grpc::CallbackServerContext* context, grpc::ByteBuffer* response) {
  return new UploadReactor(&state_, context, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::Consolidate(
    grpc::CallbackServerContext* context, const v1::ConsolidateRequest* request,
    v1::ConsolidateResponse* response) {
  return RunUnary(context, auth::Action::kConsolidate, request->fleet_id(), {},
                  [this, request, response]() -> absl::Status {
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
  return RunUnary(context, auth::Action::kSample, request->fleet_id(),
                  request->robot_id(),
                  [this, request, response]() -> absl::Status {
                    absl::StatusOr<std::vector<core::MemoryTrace>> traces =
                        state_.engine().SampleReplay(
                            request->fleet_id(), request->robot_id(),
                            request->count(), request->request_id());
                    if (!traces.ok()) return traces.status();
                    SampledTracesToProto(*traces, response);
                    return absl::OkStatus();
                  });
}

grpc::ServerUnaryReactor* MemoryServiceImpl::QueryPlace(
    grpc::CallbackServerContext* context, const v1::QueryPlaceRequest* request,
    v1::QueryPlaceResponse* response) {
  return RunUnary(context, auth::Action::kQuery, request->fleet_id(), {},
                  [this, request, response]() -> absl::Status {
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
  return new WatchReactor(&state_, *context, *request);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::GetStats(
    grpc::CallbackServerContext* context, const v1::GetStatsRequest* request,
    v1::GetStatsResponse* response) {
  return RunUnary(context, auth::Action::kStats, request->fleet_id(), {},
                  [this, request, response]() -> absl::Status {
                    absl::StatusOr<engine::FleetStats> stats =
                        state_.engine().GetStats(request->fleet_id());
                    if (!stats.ok()) return stats.status();
                    StatsToProto(*stats, response);
                    return absl::OkStatus();
                  });
}

}  // namespace fleetmem::transport
