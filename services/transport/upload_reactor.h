// UploadTraces: a client stream of trace batches for one fleet.
#ifndef FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_
#define FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_

#include <string>

#include "fleetmem/v1/memory.grpc.pb.h"
#include "grpcpp/support/server_callback.h"
#include "services/transport/service_state.h"

namespace fleetmem::transport {

// Reads one message, stores it with MemoryEngine::Upload on the worker pool,
// and only then reads the next (at most one message in flight per stream, so
// a fast client is held back by the server's storage). Finishes with the
// summed counters at the end of the stream, or with the first error: a
// message naming another fleet (INVALID_ARGUMENT), an engine error, a full
// pool (RESOURCE_EXHAUSTED), a passed deadline (DEADLINE_EXCEEDED), or a
// message arriving after shutdown began (UNAVAILABLE; messages stored before
// are durable and count as duplicates when retried).
//
// Created by the service for each call; deletes itself in OnDone. At any
// time at most one of {a gRPC reaction, the pool task} runs for a stream, so
// its fields need no lock.
class UploadReactor : public grpc::ServerReadReactor<v1::UploadTracesRequest> {
 public:
  UploadReactor(ServiceState* state, grpc::CallbackServerContext* context,
                v1::UploadTracesResponse* response);

  void OnReadDone(bool ok) override;
  void OnDone() override;

 private:
  // Runs on the worker pool.
  void Store();

  ServiceState* const state_;
  grpc::CallbackServerContext* const context_;
  v1::UploadTracesResponse* const response_;  // the running totals
  v1::UploadTracesRequest request_;
  std::string fleet_id_;  // of the first message
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_UPLOAD_REACTOR_H_
