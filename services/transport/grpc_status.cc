#include "services/transport/grpc_status.h"

#include <string>

namespace fleetmem::transport {

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  int code = static_cast<int>(status.code());
  if (code < static_cast<int>(grpc::StatusCode::OK) ||
      code > static_cast<int>(grpc::StatusCode::UNAUTHENTICATED)) {
    code = static_cast<int>(grpc::StatusCode::UNKNOWN);
  }
  return grpc::Status(static_cast<grpc::StatusCode>(code),
                      std::string(status.message()));
}

grpc::Status ServerBusyStatus() {
  return grpc::Status(grpc::StatusCode::RESOURCE_EXHAUSTED,
                      "server busy: too many calls queued; retry later");
}

grpc::Status ShuttingDownStatus() {
  return grpc::Status(grpc::StatusCode::UNAVAILABLE,
                      "server is shutting down; retry elsewhere or later");
}

grpc::Status DeadlineExceededStatus() {
  return grpc::Status(grpc::StatusCode::DEADLINE_EXCEEDED,
                      "deadline passed before the call was worked on");
}

grpc::Status CallLiveness(std::chrono::system_clock::time_point deadline,
                          bool cancelled,
                          std::chrono::system_clock::time_point now) {
  if (deadline <= now) return DeadlineExceededStatus();
  if (cancelled) {
    return grpc::Status(grpc::StatusCode::CANCELLED, "call was cancelled");
  }
  return grpc::Status::OK;
}

grpc::Status CheckCallLive(const grpc::CallbackServerContext& context) {
  return CallLiveness(context.deadline(), context.IsCancelled(),
                      std::chrono::system_clock::now());
}

}  // namespace fleetmem::transport
