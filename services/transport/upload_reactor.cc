#include "services/transport/upload_reactor.h"

#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "services/common/log.h"
#include "services/core/validation.h"
#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"

namespace fleetmem::transport {

UploadReactor::UploadReactor(ServiceState* state,
                             grpc::CallbackServerContext* context,
                             v1::UploadTracesResponse* response)
    : state_(state), context_(context), response_(response) {
  if (state_->shutting_down()) {
    Finish(ShuttingDownStatus());
    return;
  }
  StartRead(&request_);
}

void UploadReactor::OnReadDone(bool ok) {
  if (!ok) {
    // The client closed its side (or the call broke): every message read so
    // far is durable, so report the totals.
    Finish(grpc::Status::OK);
    return;
  }
  if (state_->shutting_down()) {
    Finish(ShuttingDownStatus());
    return;
  }
  if (fleet_id_.empty()) {
    absl::Status valid = core::ValidateId("fleet_id", request_.fleet_id());
    if (!valid.ok()) {
      Finish(ToGrpcStatus(valid));
      return;
    }
    fleet_id_ = request_.fleet_id();
  } else if (request_.fleet_id() != fleet_id_) {
    Finish(grpc::Status(
        grpc::StatusCode::INVALID_ARGUMENT,
        absl::StrCat("fleet_id: every message of an UploadTraces stream must "
                     "name the same fleet; got \"",
                     request_.fleet_id(), "\" after \"", fleet_id_, "\"")));
    return;
  }
  if (!state_->work().TrySubmit([this] { Store(); })) {
    Finish(ServerBusyStatus());
  }
}

void UploadReactor::Store() {
  grpc::Status live = CheckCallLive(*context_);
  if (!live.ok()) {
    Finish(live);
    return;
  }
  std::vector<core::MemoryTrace> traces =
      UploadedTracesFromProto(request_.traces());
  absl::StatusOr<engine::UploadResult> result =
      state_->engine().Upload(fleet_id_, traces);
  if (!result.ok()) {
    FLEETMEM_LOG(kDebug) << "UploadTraces " << fleet_id_ << ": "
                         << result.status();
    Finish(ToGrpcStatus(result.status()));
    return;
  }
  AddUploadResult(*result, response_);
  StartRead(&request_);
}

void UploadReactor::OnDone() { delete this; }

}  // namespace fleetmem::transport
