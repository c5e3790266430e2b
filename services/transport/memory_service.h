// fleetmem.v1.MemoryService on gRPC's callback API. Each handler translates
// proto -> domain, runs the engine call on the worker pool (engine calls
// block on fsync; gRPC's callback threads never do), translates the result
// back and finishes with the engine's status.
//
// Every call is authenticated and authorised first (call_auth.h):
//   UNAUTHENTICATED     no, unknown or wrong credentials (auth on).
//   PERMISSION_DENIED   outside the caller's role or fleets.
// Every call is answered:
//   UNAVAILABLE         after Shutdown().
//   RESOURCE_EXHAUSTED  "server busy" when the pool's queue is full.
//   DEADLINE_EXCEEDED   when the deadline passed while the call was queued
//                       (the work is then not done).
#ifndef FLEETMEM_SERVICES_TRANSPORT_MEMORY_SERVICE_H_
#define FLEETMEM_SERVICES_TRANSPORT_MEMORY_SERVICE_H_

#include "absl/functional/any_invocable.h"
#include "absl/status/status.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "services/auth/access_policy.h"
#include "services/auth/authenticator.h"
#include "services/engine/memory_engine.h"
#include "services/transport/service_state.h"
#include "services/transport/work_queue.h"

namespace fleetmem::transport {

// Thread-safe. Register with grpc::ServerBuilder::RegisterService. Shut down
// in this order: Shutdown(), WaitIdle(now + grace), grpc::Server::Shutdown
// (now: cancels what is left, idle connections included, without waiting
// for their GOAWAY handshake), WorkQueue::Stop(), then destroy the service,
// the engine and the store.
//
// UploadTraces and WatchMemory are registered raw (bytes in, bytes out) so
// that a message that does not parse fails the call with INVALID_ARGUMENT
// naming it, where gRPC's own parsing would end the stream as if the client
// had closed it (an upload) or answer UNIMPLEMENTED (a watch).
class MemoryServiceImpl final
    : public v1::MemoryService::WithRawCallbackMethod_UploadTraces<
          v1::MemoryService::WithRawCallbackMethod_WatchMemory<
              v1::MemoryService::CallbackService>> {
 public:
  // `engine`, `memory` (the mode: fleet_memory.h), `work` and
  // `authenticator` must outlive the service; a null `authenticator` turns
  // auth off.
  MemoryServiceImpl(engine::MemoryEngine* engine, FleetMemory* memory,
                    WorkQueue* work,
                    const auth::Authenticator* authenticator = nullptr,
                    ServiceOptions options = {});

  // New calls get UNAVAILABLE, upload streams end at their next message with
  // UNAVAILABLE, and every watch finishes at once with UNAVAILABLE. Calls
  // already on the pool complete. Idempotent.
  void Shutdown();
  // Distributed mode: ends the watches of a fleet this replica lost.
  void EndWatches(std::string_view fleet_id) { state_.EndWatches(fleet_id); }

  // After Shutdown: blocks until no call is being worked on (a unary call
  // queued or running, an upload message being stored) or until `deadline`;
  // true if idle. Idle connections and upload streams waiting for their
  // client's next message do not count: the server may then cancel them at
  // once (grpc::Server::Shutdown with a past deadline).
  bool WaitIdle(absl::Time deadline);

  // The unary calls this service runs, for another transport (the HTTP
  // gateway) to serve the same functions.
  MemoryApi& api() { return state_.api(); }

  grpc::ServerReadReactor<grpc::ByteBuffer>* UploadTraces(
      grpc::CallbackServerContext* context,
      grpc::ByteBuffer* response) override;
  // Raw too: a request that does not parse is INVALID_ARGUMENT (gRPC's
  // generated handler answered UNIMPLEMENTED).
  grpc::ServerWriteReactor<grpc::ByteBuffer>* WatchMemory(
      grpc::CallbackServerContext* context,
      const grpc::ByteBuffer* request) override;

 private:
  // The unary methods are served raw (bytes in, bytes out), so that a
  // request that does not parse is answered INVALID_ARGUMENT by RunUnary,
  // not UNIMPLEMENTED with no message by gRPC's generated handler.
  //
  // On the pool: parses the request as `method`'s input type, authenticates
  // the caller, then finishes the call's default reactor with the status of
  // MemoryApi::Call (which authorises and works); or at once with
  // UNAVAILABLE / RESOURCE_EXHAUSTED. Every answer is reported to
  // ServiceOptions::on_call.
  grpc::ServerUnaryReactor* RunUnary(
      grpc::CallbackServerContext* context,
      const google::protobuf::MethodDescriptor* method,
      const grpc::ByteBuffer* request, grpc::ByteBuffer* response);
  // RunUnary's work on the pool: the call's status, its answer in
  // *response when OK.
  grpc::Status ServeUnary(const grpc::CallbackServerContext& context,
                          const google::protobuf::MethodDescriptor& method,
                          const grpc::ByteBuffer& request,
                          grpc::ByteBuffer* response);

  ServiceState state_;
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_MEMORY_SERVICE_H_
