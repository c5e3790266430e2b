#include "services/transport/upload_checks.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"
#include "services/core/validation.h"
#include "services/transport/proto_convert.h"

namespace fleetmem::transport {

absl::Status CheckUploadFleet(const v1::UploadTracesRequest& request,
                              std::string_view bound) {
  if (bound.empty()) return core::ValidateId("fleet_id", request.fleet_id());
  if (request.fleet_id() == bound) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(
      "fleet_id: every message of an UploadTraces stream must name the "
      "same fleet; got \"",
      request.fleet_id(), "\" after \"", V(bound), "\""));
}

absl::StatusOr<CheckedUpload> CheckUploadTraces(
    const auth::Principal& caller, const v1::UploadTracesRequest& request) {
  if (absl::Status allowed =
          auth::Authorize(caller, auth::Action::kUpload, request.fleet_id());
      !allowed.ok()) {
    return allowed;
  }
  for (int i = 0; i < request.traces_size(); ++i) {
    absl::Status allowed =
        auth::AuthorizeUploadAs(caller, request.traces(i).robot_id());
    if (!allowed.ok()) {
      return absl::PermissionDeniedError(
          absl::StrCat("traces[", i, "]: ", allowed.message()));
    }
  }
  CheckedUpload checked;
  checked.traces = UploadedTracesFromProto(request.traces());
  checked.wait_applied = request.ack() == v1::UPLOAD_ACK_APPLIED;
  return checked;
}

absl::StatusOr<CheckedUpload> CheckUpload(
    const auth::Principal& caller, const v1::UploadTracesRequest& request) {
  if (absl::Status fleet = CheckUploadFleet(request); !fleet.ok()) {
    return fleet;
  }
  return CheckUploadTraces(caller, request);
}

}  // namespace fleetmem::transport
