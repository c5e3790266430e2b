// Thin helpers over the generated fleetmem.v1 stubs for the integration
// tests. Every call carries a deadline. Deliberately not the client library:
// the tests talk to the server as an independent client would.
#ifndef FLEETMEM_TESTS_API_HELPERS_H_
#define FLEETMEM_TESTS_API_HELPERS_H_

#include <chrono>
#include <cstdint>
#include <memory>
#include <ostream>
#include <span>
#include <string>
#include <vector>

#include "fleetmem/v1/memory.grpc.pb.h"
#include "fleetmem/v1/memory.pb.h"
#include "grpcpp/grpcpp.h"

namespace fleetmem::testing {

// Deadline of an ordinary test call.
inline constexpr std::chrono::milliseconds kCallDeadline{20000};

// A context whose deadline is now + `timeout`.
std::unique_ptr<grpc::ClientContext> MakeContext(
    std::chrono::milliseconds timeout = kCallDeadline);

// Status and response of one call.
template <typename Response>
struct Reply {
  grpc::Status status;
  Response response;
  bool ok() const { return status.ok(); }
};

// "CODE: message" for failure messages.
std::string Describe(const grpc::Status& status);

// An insecure channel and stub to `address` ("host:port").
std::unique_ptr<v1::MemoryService::Stub> MakeStub(const std::string& address);
std::shared_ptr<grpc::Channel> MakeChannel(const std::string& address);

// One UploadTraces stream carrying `requests` in order, each applied before
// its answer unless it sets `ack` (UPLOAD_ACK_APPLIED for UNSPECIFIED). Stops
// writing at the first failed Write (the status then tells why).
Reply<v1::UploadTracesResponse> Upload(
    v1::MemoryService::StubInterface& stub,
    std::span<const v1::UploadTracesRequest> requests,
    std::chrono::milliseconds timeout = kCallDeadline);

// `traces` of one fleet in one stream, in messages of `batch` traces.
Reply<v1::UploadTracesResponse> UploadTraces(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    std::span<const v1::MemoryTrace> traces, size_t batch = 500,
    std::chrono::milliseconds timeout = kCallDeadline);

Reply<v1::GetStatsResponse> GetStats(v1::MemoryService::StubInterface& stub,
                                     const std::string& fleet_id);
// GetStats once the fleet's log is applied through every upload it has
// acknowledged (uploads acknowledged as durable are applied a moment
// later), or after `wait` with what it had then (backlog_traces > 0).
Reply<v1::GetStatsResponse> GetStatsApplied(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    std::chrono::milliseconds wait = std::chrono::seconds(120));
Reply<v1::ConsolidateResponse> Consolidate(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id);
Reply<v1::SampleReplayResponse> SampleReplay(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    const std::string& robot_id, uint32_t count);
Reply<v1::QueryPlaceResponse> QueryPlace(v1::MemoryService::StubInterface& stub,
                                         const v1::QueryPlaceRequest& request);
// QueryPlace without a position prior.
Reply<v1::QueryPlaceResponse> QueryCode(v1::MemoryService::StubInterface& stub,
                                        const std::string& fleet_id,
                                        std::span<const float> code,
                                        uint32_t k);

// Reads WatchMemory(fleet_id, after_event) until an event with
// id >= until_event arrived (then cancels the call), or until `max_events`
// events arrived, or the call ended (deadline `timeout`). `status` is OK if
// the reading stopped because of one of the two limits.
Reply<std::vector<v1::MemoryEvent>> ReadEvents(
    v1::MemoryService::StubInterface& stub, const std::string& fleet_id,
    uint64_t after_event, uint64_t until_event, size_t max_events = SIZE_MAX,
    std::chrono::milliseconds timeout = kCallDeadline);

// The robot's entry of `stats`, or nullptr.
const v1::RobotStats* FindRobot(const v1::GetStatsResponse& stats,
                                const std::string& robot_id);

// code as a vector.
std::vector<float> CodeOf(const v1::MemoryTrace& trace);

// Calls `method` ("/pkg.Service/Method") with the serialised `request`
// through the generic stub; the raw answer goes to `response`.
grpc::Status GenericUnaryCall(grpc::Channel* channel, const std::string& method,
                              const std::string& request,
                              std::string* response);

// One streaming call of `method` through the generic stub: writes `messages`
// (raw bytes) in order, half-closes, reads one response into `response`.
grpc::Status GenericStreamCall(std::shared_ptr<grpc::Channel> channel,
                               const std::string& method,
                               const std::vector<std::string>& messages,
                               std::string* response);

// One ServerReflectionInfo exchange (`method` names v1alpha or v1) with a
// list_services request.
grpc::Status ListServicesByReflection(std::shared_ptr<grpc::Channel> channel,
                                      const std::string& method,
                                      std::string* response);

}  // namespace fleetmem::testing

namespace grpc {
// Lets gtest print statuses.
void PrintTo(const Status& status, std::ostream* out);
}  // namespace grpc

#endif  // FLEETMEM_TESTS_API_HELPERS_H_
