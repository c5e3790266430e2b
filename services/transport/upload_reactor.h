// UploadTraces: a client stream of trace batches for one fleet.
#ifndef FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_
#define FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_

#include <cstdint>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "grpcpp/support/byte_buffer.h"
#include "grpcpp/support/server_callback.h"
#include "services/auth/access_policy.h"
#include "services/transport/service_state.h"

namespace fleetmem::transport {

// Parses one message of an upload stream. INVALID_ARGUMENT if the bytes are
// not an UploadTracesRequest (the reactor adds which message it was).
absl::StatusOr<v1::UploadTracesRequest> ParseUploadMessage(
    absl::string_view bytes);

// Reads one message (raw bytes), parses it, stores it with
// MemoryEngine::Upload on the worker pool, and only then reads the next (at
// most one message in flight per stream, so a fast client is held back by
// the server's storage). Finishes with the summed counters at the end of the
// stream, or with the first error, which names the message ("message 3 of
// the stream: ...") and says what the messages before it did (they are
// durable and count as duplicates when retried):
//   INVALID_ARGUMENT    a message that does not parse, names another fleet
//                       or fails validation (nothing of it is stored);
//   UNAUTHENTICATED / PERMISSION_DENIED   the access policy (a robot uploads
//                       only traces of its own robot id);
//   RESOURCE_EXHAUSTED  a full pool, the client's open streams
//                       (max_streams_per_client) or an upload quota;
//   DEADLINE_EXCEEDED   a passed deadline;
//   UNAVAILABLE         a message arriving after shutdown began;
//   the engine's error otherwise (e.g. a failed write: nothing of that
//   message is stored).
//
// Created by the service for each call; deletes itself in OnDone. At any
// time at most one of {a gRPC reaction, the pool task} runs for a stream, so
// its fields need no lock.
class UploadReactor : public grpc::ServerReadReactor<grpc::ByteBuffer> {
 public:
  UploadReactor(ServiceState* state, grpc::CallbackServerContext* context,
                grpc::ByteBuffer* response);

  void OnReadDone(bool ok) override;
  void OnDone() override;

 private:
  // Runs on the worker pool.
  void Store();
  // Finishes with `status` for the current message: "message N of the
  // stream: ..." plus Earlier().
  void Fail(const absl::Status& status);
  // Finish, reported to ServiceOptions::on_call.
  void Done(const grpc::Status& status);
  // What the messages before the current one did, as a suffix.
  std::string Earlier() const;

  ServiceState* const state_;
  grpc::CallbackServerContext* const context_;
  grpc::ByteBuffer* const response_;
  grpc::ByteBuffer buffer_;          // the message being read
  v1::UploadTracesRequest request_;  // ... parsed
  v1::UploadTracesResponse totals_;  // the running totals
  uint64_t index_ = 0;               // 1-based number of the current message
  std::string fleet_id_;             // of the first message
  std::optional<auth::Principal> principal_;  // once authenticated
  std::string client_;                        // holds a stream slot if set
  size_t message_bytes_ = 0;                  // of the message being stored
  const absl::Time started_ = absl::Now();
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_
