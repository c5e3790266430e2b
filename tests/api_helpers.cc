#include "tests/api_helpers.h"

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <thread>

#include "absl/strings/str_cat.h"
#include "grpcpp/generic/generic_stub.h"
#include "grpcpp/support/byte_buffer.h"

namespace fleetmem::testing {
namespace {

const char* CodeName(grpc::StatusCode code) {
  switch (code) {
    case grpc::StatusCode::OK:
      return "OK";
    case grpc::StatusCode::CANCELLED:
      return "CANCELLED";
    case grpc::StatusCode::UNKNOWN:
      return "UNKNOWN";
    case grpc::StatusCode::INVALID_ARGUMENT:
      return "INVALID_ARGUMENT";
    case grpc::StatusCode::DEADLINE_EXCEEDED:
      return "DEADLINE_EXCEEDED";
    case grpc::StatusCode::NOT_FOUND:
      return "NOT_FOUND";
    case grpc::StatusCode::ALREADY_EXISTS:
      return "ALREADY_EXISTS";
    case grpc::StatusCode::PERMISSION_DENIED:
      return "PERMISSION_DENIED";
    case grpc::StatusCode::RESOURCE_EXHAUSTED:
      return "RESOURCE_EXHAUSTED";
    case grpc::StatusCode::FAILED_PRECONDITION:
      return "FAILED_PRECONDITION";
    case grpc::StatusCode::ABORTED:
      return "ABORTED";
    case grpc::StatusCode::OUT_OF_RANGE:
      return "OUT_OF_RANGE";
    case grpc::StatusCode::UNIMPLEMENTED:
      return "UNIMPLEMENTED";
    case grpc::StatusCode::INTERNAL:
      return "INTERNAL";
    case grpc::StatusCode::UNAVAILABLE:
      return "UNAVAILABLE";
    case grpc::StatusCode::DATA_LOSS:
      return "DATA_LOSS";
    case grpc::StatusCode::UNAUTHENTICATED:
      return "UNAUTHENTICATED";
    default:
      return "?";
  }
}

}  // namespace

std::unique_ptr<grpc::ClientContext> MakeContext(
    std::chrono::milliseconds timeout) {
  auto context = std::make_unique<grpc::ClientContext>();
  context->set_deadline(std::chrono::system_clock::now() + timeout);
  return context;
}

std::string Describe(const grpc::Status& status) {
  return absl::StrCat(CodeName(status.error_code()), ": ",
                      status.error_message());
}

std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address) {
  grpc::ChannelArguments arguments;
  // Large enough for SampleReplay of every trace of a test fleet.
  arguments.SetMaxReceiveMessageSize(64 << 20);
  return grpc::CreateCustomChannel(address, grpc::InsecureChannelCredentials(),
                                   arguments);
}

std::unique_ptr<v1::MemoryService::Stub> MakeStub(const std::string& address) {
  return v1::MemoryService::NewStub(MakeChannel(address));
}

Reply<v1::UploadTracesResponse> Upload(
    v1::MemoryService::StubInterface& stub,
    std::span<const v1::UploadTracesRequest> requests,
    std::chrono::milliseconds timeout) {
  Reply<v1::UploadTracesResponse> reply;
  auto context = MakeContext(timeout);
  std::unique_ptr<grpc::ClientWriterInterface<v1::UploadTracesRequest>> writer =
      stub.UploadTraces(context.get(), &reply.response);
  for (v1::UploadTracesRequest request : requests) {
    // Read-your-writes unless the test says otherwise: these tests read
    // what they uploaded.
    if (request.ack() == v1::UPLOAD_ACK_UNSPECIFIED) {
      request.set_ack(v1::UPLOAD_ACK_APPLIED);
    }
    if (!writer->Write(request)) break;
  }
  writer->WritesDone();
  reply.status = writer->Finish();
  return reply;
}

Reply<v1::UploadTracesResponse> UploadTraces(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    std::span<const v1::MemoryTrace> traces, size_t batch,
    std::chrono::milliseconds timeout) {
  std::vector<v1::UploadTracesRequest> requests;
  if (batch == 0) batch = 1;
  for (size_t begin = 0; begin < traces.size(); begin += batch) {
    v1::UploadTracesRequest& request = requests.emplace_back();
    request.set_fleet_id(fleet_id);
    for (size_t i = begin; i < std::min(traces.size(), begin + batch); ++i) {
      *request.add_traces() = traces[i];
    }
  }
  return Upload(stub, requests, timeout);
}

Reply<v1::GetStatsResponse> GetStats(v1::MemoryService::StubInterface& stub,
                                     const std::string& fleet_id) {
  Reply<v1::GetStatsResponse> reply;
  v1::GetStatsRequest request;
  request.set_fleet_id(fleet_id);
  auto context = MakeContext();
  reply.status = stub.GetStats(context.get(), request, &reply.response);
  return reply;
}

Reply<v1::GetStatsResponse> GetStatsApplied(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    std::chrono::milliseconds wait) {
  const auto give_up = std::chrono::steady_clock::now() + wait;
  Reply<v1::GetStatsResponse> stats = GetStats(stub, fleet_id);
  while (stats.ok() &&
         stats.response.applied_through() <
             stats.response.acknowledged_through() &&
         std::chrono::steady_clock::now() < give_up) {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    stats = GetStats(stub, fleet_id);
  }
  return stats;
}

Reply<v1::ConsolidateResponse> Consolidate(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id) {
  Reply<v1::ConsolidateResponse> reply;
  v1::ConsolidateRequest request;
  request.set_fleet_id(fleet_id);
  auto context = MakeContext();
  reply.status = stub.Consolidate(context.get(), request, &reply.response);
  return reply;
}

Reply<v1::SampleReplayResponse> SampleReplay(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    const std::string& robot_id, uint32_t count) {
  Reply<v1::SampleReplayResponse> reply;
  v1::SampleReplayRequest request;
  request.set_fleet_id(fleet_id);
  request.set_robot_id(robot_id);
  request.set_count(count);
  auto context = MakeContext();
  reply.status = stub.SampleReplay(context.get(), request, &reply.response);
  return reply;
}

Reply<v1::QueryPlaceResponse> QueryPlace(v1::MemoryService::StubInterface& stub,
                                         const v1::QueryPlaceRequest& request) {
  Reply<v1::QueryPlaceResponse> reply;
  auto context = MakeContext();
  reply.status = stub.QueryPlace(context.get(), request, &reply.response);
  return reply;
}

Reply<v1::QueryPlaceResponse> QueryCode(v1::MemoryService::StubInterface& stub,
                                        const std::string& fleet_id,
                                        std::span<const float> code,
                                        uint32_t k) {
  v1::QueryPlaceRequest request;
  request.set_fleet_id(fleet_id);
  for (float value : code) request.add_code(value);
  request.set_k(k);
  return QueryPlace(stub, request);
}

Reply<std::vector<v1::MemoryEvent>> ReadEvents(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    uint64_t after_event, uint64_t until_event, size_t max_events,
    std::chrono::milliseconds timeout) {
  Reply<std::vector<v1::MemoryEvent>> reply;
  v1::WatchMemoryRequest request;
  request.set_fleet_id(fleet_id);
  request.set_after_event(after_event);
  auto context = MakeContext(timeout);
  std::unique_ptr<grpc::ClientReaderInterface<v1::MemoryEvent>> reader =
      stub.WatchMemory(context.get(), request);
  bool limit_reached = until_event == 0 && max_events == 0;
  v1::MemoryEvent event;
  while (!limit_reached && reader->Read(&event)) {
    reply.response.push_back(event);
    limit_reached = (until_event != 0 && event.id() >= until_event) ||
                    reply.response.size() >= max_events;
  }
  if (limit_reached) {
    context->TryCancel();
    reader->Finish();
    reply.status = grpc::Status::OK;
  } else {
    reply.status = reader->Finish();
  }
  return reply;
}

const v1::RobotStats* FindRobot(const v1::GetStatsResponse& stats,
                                const std::string& robot_id) {
  for (const v1::RobotStats& robot : stats.robots()) {
    if (robot.robot_id() == robot_id) return &robot;
  }
  return nullptr;
}

std::vector<float> CodeOf(const v1::MemoryTrace& trace) {
  return std::vector<float>(trace.code().begin(), trace.code().end());
}

grpc::Status GenericUnaryCall(grpc::Channel* channel, const std::string& method,
                              const std::string& request,
                              std::string* response) {
  grpc::GenericStub generic(channel->shared_from_this());
  grpc::Slice slice(request);
  grpc::ByteBuffer request_buffer(&slice, 1);
  grpc::ByteBuffer response_buffer;
  auto context = MakeContext();
  std::mutex mu;
  std::condition_variable cv;
  bool done = false;
  grpc::Status status;
  generic.UnaryCall(context.get(), method, grpc::StubOptions(), &request_buffer,
                    &response_buffer, [&](grpc::Status s) {
                      std::lock_guard<std::mutex> lock(mu);
                      status = std::move(s);
                      done = true;
                      cv.notify_all();
                    });
  std::unique_lock<std::mutex> lock(mu);
  cv.wait(lock, [&] { return done; });  // the context's deadline bounds this
  if (status.ok()) {
    std::vector<grpc::Slice> slices;
    response_buffer.Dump(&slices);
    response->clear();
    for (const grpc::Slice& s : slices) {
      response->append(reinterpret_cast<const char*>(s.begin()), s.size());
    }
  }
  return status;
}

grpc::Status GenericStreamCall(std::shared_ptr<grpc::Channel> channel,
                               const std::string& method,
                               const std::vector<std::string>& messages,
                               std::string* response) {
  grpc::GenericStub generic(channel);
  grpc::CompletionQueue queue;
  auto context = MakeContext();
  std::unique_ptr<grpc::GenericClientAsyncReaderWriter> call =
      generic.PrepareCall(context.get(), method, &queue);
  // Each step is started and then awaited; the deadline bounds every wait.
  auto await = [&queue](intptr_t expected) {
    void* tag = nullptr;
    bool ok = false;
    if (!queue.Next(&tag, &ok)) return false;
    return ok && reinterpret_cast<intptr_t>(tag) == expected;
  };
  grpc::ByteBuffer reply;
  call->StartCall(reinterpret_cast<void*>(1));
  bool ok = await(1);
  for (const std::string& message : messages) {
    if (!ok) break;
    grpc::Slice slice(message);
    grpc::ByteBuffer request(&slice, 1);
    call->Write(request, reinterpret_cast<void*>(2));
    ok = await(2);
  }
  if (ok) {
    call->WritesDone(reinterpret_cast<void*>(3));
    ok = await(3);
  }
  bool got_reply = false;
  if (ok) {
    call->Read(&reply, reinterpret_cast<void*>(4));
    got_reply = await(4);
  }
  grpc::Status status;
  call->Finish(&status, reinterpret_cast<void*>(5));
  void* tag = nullptr;
  bool finished = false;
  while (queue.Next(&tag, &finished)) {
    if (reinterpret_cast<intptr_t>(tag) == 5) break;
  }
  queue.Shutdown();
  while (queue.Next(&tag, &finished)) {
  }
  response->clear();
  if (got_reply) {
    std::vector<grpc::Slice> slices;
    reply.Dump(&slices);
    for (const grpc::Slice& s : slices) {
      response->append(reinterpret_cast<const char*>(s.begin()), s.size());
    }
  }
  if (status.ok() && !got_reply) {
    return grpc::Status(grpc::StatusCode::UNKNOWN, "no response");
  }
  return status;
}

grpc::Status ListServicesByReflection(std::shared_ptr<grpc::Channel> channel,
                                      const std::string& method,
                                      std::string* response) {
  // ServerReflectionRequest{list_services: ""}: field 7, length 0.
  return GenericStreamCall(channel, method, {std::string("\x3a\x00", 2)},
                           response);
}

}  // namespace fleetmem::testing

namespace grpc {
void PrintTo(const Status& status, std::ostream* out) {
  *out << fleetmem::testing::Describe(status);
}
}  // namespace grpc
