#include "services/transport/memory_service.h"

#include <utility>
#include <vector>

#include "absl/time/clock.h"
#include "services/transport/call_auth.h"
#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_reactor.h"
#include "services/transport/watch_reactor.h"

namespace fleetmem::transport {

MemoryServiceImpl::MemoryServiceImpl(engine::MemoryEngine* engine,
                                     FleetMemory* memory, WorkQueue* work,
                                     const auth::Authenticator* authenticator,
                                     ServiceOptions options)
    : state_(engine, memory, work, authenticator, options) {}

void MemoryServiceImpl::Shutdown() { state_.Shutdown(); }

bool MemoryServiceImpl::WaitIdle(absl::Time deadline) {
  return state_.WaitIdle(deadline);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::RunUnary(
    grpc::CallbackServerContext* context, const char* method,
    const google::protobuf::Message* request,
    google::protobuf::Message* response) {
  const absl::Time started = absl::Now();
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  auto finish = [this, reactor, method, started](const grpc::Status& status) {
    state_.ObserveCall(
        method, static_cast<absl::StatusCode>(status.error_code()), started);
    reactor->Finish(status);
  };
  if (state_.shutting_down()) {
    finish(ShuttingDownStatus());
    return reactor;
  }
  state_.BeginWork();
  bool queued = state_.work().TrySubmit(
      [this, context, method, request, response, finish]() mutable {
        finish([&] {
          grpc::Status live = CheckCallLive(*context);
          if (!live.ok()) return live;
          absl::StatusOr<auth::Principal> caller =
              AuthenticateCall(state_.authenticator(), *context);
          if (!caller.ok()) return ToGrpcStatus(caller.status());
          const bool forwarded =
              context->client_metadata().count(kForwardedHeader) > 0;
          return ToGrpcStatus(state_.api().Call(method, *caller, *request,
                                                response, forwarded));
        }());
        state_.EndWork();
      });
  if (!queued) {
    state_.EndWork();
    finish(ServerBusyStatus());
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
  return RunUnary(context, "Consolidate", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::SampleReplay(
    grpc::CallbackServerContext* context,
    const v1::SampleReplayRequest* request,
    v1::SampleReplayResponse* response) {
  return RunUnary(context, "SampleReplay", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::QueryPlace(
    grpc::CallbackServerContext* context, const v1::QueryPlaceRequest* request,
    v1::QueryPlaceResponse* response) {
  return RunUnary(context, "QueryPlace", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::GetStats(
    grpc::CallbackServerContext* context, const v1::GetStatsRequest* request,
    v1::GetStatsResponse* response) {
  return RunUnary(context, "GetStats", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::ListFleets(
    grpc::CallbackServerContext* context, const v1::ListFleetsRequest* request,
    v1::ListFleetsResponse* response) {
  return RunUnary(context, "ListFleets", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::ListClusters(
    grpc::CallbackServerContext* context,
    const v1::ListClustersRequest* request,
    v1::ListClustersResponse* response) {
  return RunUnary(context, "ListClusters", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::ListEvents(
    grpc::CallbackServerContext* context, const v1::ListEventsRequest* request,
    v1::ListEventsResponse* response) {
  return RunUnary(context, "ListEvents", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::ListTraces(
    grpc::CallbackServerContext* context, const v1::ListTracesRequest* request,
    v1::ListTracesResponse* response) {
  return RunUnary(context, "ListTraces", request, response);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::CreateSnapshot(
    grpc::CallbackServerContext* context,
    const v1::CreateSnapshotRequest* request,
    v1::CreateSnapshotResponse* response) {
  return RunUnary(context, "CreateSnapshot", request, response);
}

grpc::ServerWriteReactor<v1::MemoryEvent>* MemoryServiceImpl::WatchMemory(
    grpc::CallbackServerContext* context,
    const v1::WatchMemoryRequest* request) {
  return new WatchReactor(&state_, *context, *request);
}

}  // namespace fleetmem::transport
