#include "services/transport/memory_service.h"

#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "google/protobuf/descriptor.h"
#include "google/protobuf/message.h"
#include "grpcpp/support/proto_buffer_reader.h"
#include "services/transport/call_auth.h"
#include "services/transport/grpc_status.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_reactor.h"
#include "services/transport/watch_reactor.h"

namespace fleetmem::transport {

MemoryServiceImpl::MemoryServiceImpl(engine::MemoryEngine* engine,
                                     FleetMemory* memory, WorkQueue* work,
                                     const auth::Authenticator* authenticator,
                                     ServiceOptions options)
    : state_(engine, memory, work, authenticator, options) {
  // The generated service registered its methods in the proto's order.
  const google::protobuf::ServiceDescriptor* service =
      google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(
          v1::MemoryService::service_full_name());
  for (int i = 0; i < service->method_count(); ++i) {
    const google::protobuf::MethodDescriptor* method = service->method(i);
    if (method->client_streaming() || method->server_streaming()) continue;
    MarkMethodRawCallback(
        i, new grpc::internal::CallbackUnaryHandler<grpc::ByteBuffer,
                                                    grpc::ByteBuffer>(
               [this, method](grpc::CallbackServerContext* context,
                              const grpc::ByteBuffer* request,
                              grpc::ByteBuffer* response) {
                 return RunUnary(context, method, request, response);
               }));
  }
}

void MemoryServiceImpl::Shutdown() { state_.Shutdown(); }

bool MemoryServiceImpl::WaitIdle(absl::Time deadline) {
  return state_.WaitIdle(deadline);
}

grpc::ServerUnaryReactor* MemoryServiceImpl::RunUnary(
    grpc::CallbackServerContext* context,
    const google::protobuf::MethodDescriptor* method,
    const grpc::ByteBuffer* request, grpc::ByteBuffer* response) {
  const absl::Time started = absl::Now();
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  // `method` (a descriptor of the generated pool) outlives the call; a
  // reference to a local would not outlive RunUnary.
  auto finish = [this, reactor, method, started](const grpc::Status& status) {
    state_.ObserveCall(method->name(),
                       static_cast<absl::StatusCode>(status.error_code()),
                       started);
    reactor->Finish(status);
  };
  if (state_.shutting_down()) {
    finish(ShuttingDownStatus());
    return reactor;
  }
  state_.BeginWork();
  bool queued = state_.work().TrySubmit(
      [this, context, method, request, response, finish]() mutable {
        finish(ServeUnary(*context, *method, *request, response));
        state_.EndWork();
      });
  if (!queued) {
    state_.EndWork();
    finish(ServerBusyStatus());
  }
  return reactor;
}

grpc::Status MemoryServiceImpl::ServeUnary(
    const grpc::CallbackServerContext& context,
    const google::protobuf::MethodDescriptor& method,
    const grpc::ByteBuffer& request, grpc::ByteBuffer* response) {
  grpc::Status live = CheckCallLive(context);
  if (!live.ok()) return live;
  google::protobuf::MessageFactory* factory =
      google::protobuf::MessageFactory::generated_factory();
  std::unique_ptr<google::protobuf::Message> in(
      factory->GetPrototype(method.input_type())->New());
  grpc::ByteBuffer bytes(request);  // shares the slices
  grpc::ProtoBufferReader reader(&bytes);
  if (!in->ParseFromZeroCopyStream(&reader)) {
    return ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("request: ", request.Length(), " bytes do not parse as ",
                     method.input_type()->full_name(), "; nothing was done")));
  }
  absl::StatusOr<auth::Principal> caller =
      AuthenticateCall(state_.authenticator(), context);
  if (!caller.ok()) return ToGrpcStatus(caller.status());
  CallOptions how;
  how.forwarded = context.client_metadata().count(kForwardedHeader) > 0;
  how.deadline = absl::FromChrono(context.deadline());
  std::unique_ptr<google::protobuf::Message> out(
      factory->GetPrototype(method.output_type())->New());
  grpc::Status status = ToGrpcStatus(
      state_.api().Call(method.name(), *caller, *in, out.get(), how));
  if (status.ok()) {
    grpc::Slice slice(out->SerializeAsString());
    *response = grpc::ByteBuffer(&slice, 1);
  }
  return status;
}

grpc::ServerReadReactor<grpc::ByteBuffer>* MemoryServiceImpl::UploadTraces(
    grpc::CallbackServerContext* context, grpc::ByteBuffer* response) {
  return new UploadReactor(&state_, context, response);
}

namespace {

// A watch refused before it starts: finishes at once with `status`.
class RefusedWatch : public grpc::ServerWriteReactor<grpc::ByteBuffer> {
 public:
  explicit RefusedWatch(const grpc::Status& status) { Finish(status); }
  void OnDone() override { delete this; }
};

}  // namespace

grpc::ServerWriteReactor<grpc::ByteBuffer>* MemoryServiceImpl::WatchMemory(
    grpc::CallbackServerContext* context, const grpc::ByteBuffer* request) {
  v1::WatchMemoryRequest parsed;
  grpc::ByteBuffer bytes(*request);  // shares the slices
  grpc::ProtoBufferReader reader(&bytes);
  if (!parsed.ParseFromZeroCopyStream(&reader)) {
    return new RefusedWatch(ToGrpcStatus(absl::InvalidArgumentError(
        absl::StrCat("request: ", request->Length(),
                     " bytes do not parse as fleetmem.v1.WatchMemoryRequest; "
                     "nothing was done"))));
  }
  return new WatchReactor(&state_, context, parsed);
}

}  // namespace fleetmem::transport
