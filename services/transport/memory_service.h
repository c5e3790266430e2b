// fleetmem.v1.MemoryService on gRPC's callback API. Each handler translates
// proto -> domain, runs the engine call on the worker pool (engine calls
// block on fsync; gRPC's callback threads never do), translates the result
// back and finishes with the engine's status.
//
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
#include "services/engine/memory_engine.h"
#include "services/transport/service_state.h"
#include "services/transport/work_queue.h"

namespace fleetmem::transport {

// Thread-safe. Register with grpc::ServerBuilder::RegisterService. Shut down
// in this order: Shutdown(), grpc::Server::Shutdown(deadline) (it waits for
// the calls in flight, which still need `work`), WorkQueue::Stop(), then
// destroy the service, the engine and the store.
class MemoryServiceImpl final : public v1::MemoryService::CallbackService {
 public:
  // `engine` and `work` must outlive the service.
  MemoryServiceImpl(engine::MemoryEngine* engine, WorkQueue* work);

  // New calls get UNAVAILABLE, upload streams end at their next message with
  // UNAVAILABLE, and every watch finishes at once with UNAVAILABLE. Calls
  // already on the pool complete. Idempotent.
  void Shutdown();

  grpc::ServerReadReactor<v1::UploadTracesRequest>* UploadTraces(
      grpc::CallbackServerContext* context,
      v1::UploadTracesResponse* response) override;
  grpc::ServerUnaryReactor* Consolidate(
      grpc::CallbackServerContext* context,
      const v1::ConsolidateRequest* request,
      v1::ConsolidateResponse* response) override;
  grpc::ServerUnaryReactor* SampleReplay(
      grpc::CallbackServerContext* context,
      const v1::SampleReplayRequest* request,
      v1::SampleReplayResponse* response) override;
  grpc::ServerUnaryReactor* QueryPlace(
      grpc::CallbackServerContext* context,
      const v1::QueryPlaceRequest* request,
      v1::QueryPlaceResponse* response) override;
  grpc::ServerWriteReactor<v1::MemoryEvent>* WatchMemory(
      grpc::CallbackServerContext* context,
      const v1::WatchMemoryRequest* request) override;
  grpc::ServerUnaryReactor* GetStats(grpc::CallbackServerContext* context,
                                     const v1::GetStatsRequest* request,
                                     v1::GetStatsResponse* response) override;

 private:
  // Finishes the call's default reactor with `work()`'s status, run on the
  // pool; or at once with UNAVAILABLE / RESOURCE_EXHAUSTED.
  grpc::ServerUnaryReactor* RunUnary(
      grpc::CallbackServerContext* context,
      absl::AnyInvocable<absl::Status() &&> work);

  ServiceState state_;
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_MEMORY_SERVICE_H_
