// The one place where the service's absl::Status becomes a grpc::Status, and
// where a call that is no longer worth working on is recognised.
#ifndef FLEETMEM_SERVICES_TRANSPORT_GRPC_STATUS_H_
#define FLEETMEM_SERVICES_TRANSPORT_GRPC_STATUS_H_

#include <chrono>

#include "absl/status/status.h"
#include "grpcpp/server_context.h"
#include "grpcpp/support/status.h"

namespace fleetmem::transport {

// Same code and message. absl and gRPC share the google.rpc code numbers;
// a code outside 0..16 becomes UNKNOWN.
grpc::Status ToGrpcStatus(const absl::Status& status);

// The canned answers of the transport layer.
grpc::Status ServerBusyStatus();        // RESOURCE_EXHAUSTED "server busy"
grpc::Status ShuttingDownStatus();      // UNAVAILABLE
grpc::Status DeadlineExceededStatus();  // DEADLINE_EXCEEDED

// Whether a queued call should still be worked on: DEADLINE_EXCEEDED if
// `deadline` is not after `now`, else CANCELLED if `cancelled`, else OK.
grpc::Status CallLiveness(std::chrono::system_clock::time_point deadline,
                          bool cancelled,
                          std::chrono::system_clock::time_point now);

// CallLiveness of a live server call at the current time. `context` must be
// a call that has not been finished yet.
grpc::Status CheckCallLive(const grpc::CallbackServerContext& context);

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_GRPC_STATUS_H_
