// UploadTraces: a client stream of trace batches for one fleet.
#ifndef FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_
#define FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_

#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "google/protobuf/arena.h"
#include "grpcpp/support/byte_buffer.h"
#include "grpcpp/support/server_callback.h"
#include "services/auth/access_policy.h"
#include "services/transport/service_state.h"
#include "services/transport/stream_watchdog.h"

namespace fleetmem::transport {

// Parses one message of an upload stream. INVALID_ARGUMENT if the bytes are
// not an UploadTracesRequest (the reactor adds which message it was).
absl::StatusOr<v1::UploadTracesRequest> ParseUploadMessage(
    absl::string_view bytes);
// The same from gRPC's buffer, into a message on `arena`.
absl::StatusOr<v1::UploadTracesRequest*> ParseUploadMessage(
    const grpc::ByteBuffer& buffer, google::protobuf::Arena* arena);

// Reads messages (raw bytes) and parses them on gRPC's threads, and stores
// them with FleetMemory::UploadMany on the worker pool, one store task per
// stream at a time: the messages that arrived while the previous ones were
// being written are written together (in embedded mode one group commit:
// one write and one fsync for all of them). At most kReadAhead messages
// (kReadAheadBytes) wait unstored; past that the stream is not read, so a
// fast client is held back by the server's storage. Finishes with the
// summed counters at the end of the stream, or with the first error, which
// names the message ("message 3 of the stream: ...") and says what the
// messages before it did (they are durable and count as duplicates when
// retried) and, where messages after it were written in the same store
// write, that they were stored too:
//   INVALID_ARGUMENT    a message that does not parse, names another fleet
//                       or fails validation (nothing of it is stored);
//   UNAUTHENTICATED / PERMISSION_DENIED   the access policy (a robot uploads
//                       only traces of its own robot id);
//   RESOURCE_EXHAUSTED  a full pool, the client's open streams
//                       (max_streams_per_client) or an upload quota;
//   DEADLINE_EXCEEDED   a passed deadline;
//   CANCELLED           no message (nor the end of the stream) within
//                       ServiceOptions::stream_idle_timeout;
//   UNAVAILABLE         a message arriving after shutdown began;
//   the engine's error otherwise (e.g. a failed write: nothing of that
//   message is stored).
//
// Created by the service for each call; deletes itself in OnDone. gRPC's
// reactions and the store task may run at once: `mu_` guards what both
// touch; the store task alone touches the totals and the principal.
class UploadReactor : public grpc::ServerReadReactor<grpc::ByteBuffer> {
 public:
  UploadReactor(ServiceState* state, grpc::CallbackServerContext* context,
                grpc::ByteBuffer* response);

  void OnReadDone(bool ok) override;
  void OnDone() override;

  static constexpr size_t kReadAhead = 8;
  static constexpr size_t kReadAheadBytes = size_t{32} << 20;

 private:
  // A message read, parsed, waiting to be stored; or the error it met.
  struct Message {
    uint64_t index = 0;  // 1-based in the stream
    // Parsed on an arena of its own, straight from gRPC's buffer: one
    // allocation for the message's traces rather than several a trace,
    // freed at once with the message.
    std::unique_ptr<google::protobuf::Arena> arena;
    v1::UploadTracesRequest* request = nullptr;  // on `arena`
    size_t bytes = 0;
    absl::Status error;
  };

  // Runs on the worker pool until no message waits.
  void StoreQueued();
  // Stores `batch` (in order); false if the stream was finished (with an
  // error): `this` may then be gone.
  bool StoreBatch(std::deque<Message>& batch);
  // Starts the next read if none runs, the client has not closed its side,
  // nothing failed and the read-ahead has room.
  void MaybeRead() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Finishes with `status` for message `index`: "message N of the stream:
  // ..." plus Earlier() and `after`.
  void Fail(uint64_t index, const absl::Status& status,
            std::string_view after = "");
  // Finish, once, reported to ServiceOptions::on_call.
  void Done(const grpc::Status& status);
  // What the messages before message `index` did, as a suffix.
  std::string Earlier(uint64_t index) const;

  ServiceState* const state_;
  grpc::CallbackServerContext* const context_;
  grpc::ByteBuffer* const response_;
  grpc::ByteBuffer buffer_;  // the message being read
  uint64_t read_ = 0;        // messages read (gRPC's reactions only)
  std::string fleet_id_;     // of the first message, set before any store
  std::string target_;       // the fleet it names (an alias's), set with it
  std::string client_;       // holds a stream slot if set
  auth::Principal caller_;   // authenticated before the slot is taken
  const absl::Time started_ = absl::Now();

  absl::Mutex mu_;
  std::deque<Message> queue_ ABSL_GUARDED_BY(mu_);
  size_t queued_bytes_ ABSL_GUARDED_BY(mu_) = 0;
  bool reading_ ABSL_GUARDED_BY(mu_) = false;       // a read outstanding
  bool closed_ ABSL_GUARDED_BY(mu_) = false;        // the client's side is done
  bool storing_ ABSL_GUARDED_BY(mu_) = false;       // a store task runs
  bool stop_reading_ ABSL_GUARDED_BY(mu_) = false;  // a message failed
  bool finished_ ABSL_GUARDED_BY(mu_) = false;      // Finish was called
  // Armed while a read waits for the client (stream_idle_timeout).
  StreamWatchdog idle_ ABSL_GUARDED_BY(mu_){context_};

  // The store task's.
  v1::UploadTracesResponse totals_;  // the running totals
  uint64_t stored_ = 0;              // messages stored so far
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_
