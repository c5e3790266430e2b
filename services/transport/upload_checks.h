// The checks every upload passes, once, at the edge: gRPC's UploadTraces
// stream (upload_reactor.h) and the unary path REST takes (MemoryApi::
// UploadTraces). What passes goes to the FleetMemory with its fleet id
// trusted: the write path and the log do not check it again.
//
// Two halves, because a stream names its fleet in every message but is
// bound to the first one's as soon as it is read, and authorised when its
// messages are stored: CheckUploadFleet at the read, CheckUploadTraces at
// the store. CheckUpload is both, for a single message.
#ifndef FLEETMEM_SERVICES_TRANSPORT_UPLOAD_CHECKS_H_
#define FLEETMEM_SERVICES_TRANSPORT_UPLOAD_CHECKS_H_

#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "fleetmem/v1/memory.pb.h"
#include "services/auth/access_policy.h"
#include "services/core/types.h"

namespace fleetmem::transport {

// An upload message as it leaves the checks.
struct CheckedUpload {
  // UploadedTracesFromProto's: replay_count and cluster_id cleared.
  std::vector<core::MemoryTrace> traces;
  bool wait_applied = false;  // ack UPLOAD_ACK_APPLIED
};

// The message's fleet id: a valid id (core::ValidateId) for the first
// message of a stream (`bound` empty), the stream's fleet for the later
// ones. INVALID_ARGUMENT naming fleet_id otherwise.
absl::Status CheckUploadFleet(const v1::UploadTracesRequest& request,
                              std::string_view bound = {});

// The caller may upload to the message's fleet (auth::Authorize) and as
// the robot of every trace (auth::AuthorizeUploadAs; PERMISSION_DENIED
// naming the first trace that is not its own); then the traces. Their
// content (codes, shapes) is the write path's to check against the fleet.
absl::StatusOr<CheckedUpload> CheckUploadTraces(
    const auth::Principal& caller, const v1::UploadTracesRequest& request);

// Both, for one message (the unary call, REST).
absl::StatusOr<CheckedUpload> CheckUpload(
    const auth::Principal& caller, const v1::UploadTracesRequest& request);

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_UPLOAD_CHECKS_H_
