// Integration tests of fleetmem-server's error handling (bad input, unknown
// fleets, deadlines) and of the standard gRPC services it offers (health,
// reflection), against the real server binary.
#include <chrono>
#include <cmath>
#include <condition_variable>
#include <functional>
#include <limits>
#include <memory>
#include <mutex>
#include <string>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/util/message_differencer.h"
#include "grpcpp/generic/generic_stub.h"
#include "grpcpp/support/byte_buffer.h"
#include "gtest/gtest.h"
#include "tests/api_helpers.h"
#include "tests/integration_fixture.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

using ::google::protobuf::util::MessageDifferencer;

constexpr size_t kDim = 32;
constexpr char kFleet[] = "fleet-errors";

// A fleet with 60 consolidated traces and 10 pending ones (robot-1, D = 32,
// encoder enc-v1).
class BadInputTest : public ServerTest {
 protected:
  void SetUp() override {
    ASSERT_NO_FATAL_FAILURE(ServerTest::SetUp());
    TraceSpec spec{.robot_id = "robot-1", .count = 60, .dimension = kDim};
    ASSERT_TRUE(UploadTraces(stub(), kFleet, MakeTraces(spec)).ok());
    ASSERT_TRUE(Consolidate(stub(), kFleet).ok());
    spec.first_seq = 61;
    spec.count = 10;
    ASSERT_TRUE(UploadTraces(stub(), kFleet, MakeTraces(spec)).ok());
    Reply<v1::GetStatsResponse> stats = GetStats(stub(), kFleet);
    ASSERT_TRUE(stats.ok()) << Describe(stats.status);
    before_ = stats.response;
    ASSERT_EQ(before_.pending_traces(), 10u);
  }

  // A valid trace the fleet has not seen yet.
  static v1::MemoryTrace NewTrace(uint64_t seq = 1000) {
    TraceSpec spec{.robot_id = "robot-1", .dimension = kDim};
    return MakeTrace(spec, seq);
  }

  // The fleet's stats are exactly what they were before the bad call.
  void ExpectStatsUnchanged(const std::string& what) {
    Reply<v1::GetStatsResponse> after = GetStats(stub(), kFleet);
    ASSERT_TRUE(after.ok()) << Describe(after.status);
    std::string diff;
    MessageDifferencer differencer;
    differencer.ReportDifferencesToString(&diff);
    EXPECT_TRUE(differencer.Compare(before_, after.response))
        << what << " changed the fleet:\n"
        << diff;
  }

  v1::GetStatsResponse before_;
};

// `status` has `code` and a message containing one of `words` (ignoring
// case).
void ExpectError(const std::string& what, const grpc::Status& status,
                 grpc::StatusCode code, const std::vector<std::string>& words) {
  EXPECT_EQ(status.error_code(), code) << what << ": " << Describe(status);
  const std::string message = absl::AsciiStrToLower(status.error_message());
  bool mentioned = false;
  for (const std::string& word : words) {
    mentioned =
        mentioned || absl::StrContains(message, absl::AsciiStrToLower(word));
  }
  EXPECT_TRUE(mentioned) << what << ": the message \"" << status.error_message()
                         << "\" mentions none of: "
                         << absl::StrJoin(words, ", ");
}

struct UploadCase {
  std::string name;
  // Makes the bad message from a valid one (fleet kFleet, 20 new traces).
  std::function<void(v1::UploadTracesRequest&)> corrupt;
  std::vector<std::string> words;
};

TEST_F(BadInputTest, BadUploadsAreRejectedAndChangeNothing) {
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  auto last = [](v1::UploadTracesRequest& request) -> v1::MemoryTrace& {
    return *request.mutable_traces(request.traces_size() - 1);
  };
  const std::vector<UploadCase> cases = {
      {"wrong code dimension",
       [&](auto& r) { last(r).mutable_code()->RemoveLast(); },
       {"dimension"}},
      {"empty code",
       [&](auto& r) { last(r).clear_code(); },
       {"dimension", "code"}},
      {"NaN in code",
       [&](auto& r) { last(r).set_code(3, nan); },
       {"finite", "nan"}},
      {"Inf in code",
       [&](auto& r) { last(r).set_code(0, inf); },
       {"finite", "inf"}},
      {"NaN reward", [&](auto& r) { last(r).set_reward(nan); }, {"reward"}},
      {"negative reward",
       [&](auto& r) { last(r).set_reward(-0.5f); },
       {"reward"}},
      {"Inf pose",
       [&](auto& r) { last(r).mutable_pose()->set_y(inf); },
       {"pose", "place", "finite"}},
      {"empty robot id",
       [&](auto& r) { last(r).clear_robot_id(); },
       {"robot_id", "robot id"}},
      {"robot id with a space",
       [&](auto& r) { last(r).set_robot_id("robot one"); },
       {"robot_id", "robot id"}},
      {"empty fleet id",
       [&](auto& r) { r.clear_fleet_id(); },
       {"fleet_id", "fleet id"}},
      {"fleet id of 129 characters",
       [&](auto& r) { r.set_fleet_id(std::string(129, 'f')); },
       {"fleet_id", "fleet id"}},
      {"encoder version mismatch",
       [&](auto& r) { last(r).set_encoder_version("enc-v2"); },
       {"encoder"}},
      {"more than 1,000 traces in one message",
       [&](auto& r) {
         for (uint64_t seq = 2000; seq < 2981; ++seq) {
           *r.add_traces() = NewTrace(seq);
         }
         ASSERT_EQ(r.traces_size(), 1001);
       },
       {"1000", "1,000", "too many", "at most"}},
  };
  for (const UploadCase& c : cases) {
    SCOPED_TRACE(c.name);
    std::vector<v1::MemoryTrace> fresh;
    for (uint64_t seq = 1000; seq < 1020; ++seq) fresh.push_back(NewTrace(seq));
    v1::UploadTracesRequest request = MakeUploadRequest(kFleet, fresh);
    c.corrupt(request);
    Reply<v1::UploadTracesResponse> reply =
        Upload(stub(), std::span(&request, 1));
    ExpectError(c.name, reply.status, grpc::StatusCode::INVALID_ARGUMENT,
                c.words);
    ASSERT_NO_FATAL_FAILURE(ExpectStatsUnchanged(c.name));
  }
}

TEST_F(BadInputTest, BadUploadDoesNotCreateAFleet) {
  v1::MemoryTrace trace = NewTrace();
  trace.set_code(0, std::numeric_limits<float>::quiet_NaN());
  v1::UploadTracesRequest request =
      MakeUploadRequest("fleet-never", std::span(&trace, 1));
  Reply<v1::UploadTracesResponse> reply =
      Upload(stub(), std::span(&request, 1));
  EXPECT_EQ(reply.status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << Describe(reply.status);
  EXPECT_EQ(GetStats(stub(), "fleet-never").status.error_code(),
            grpc::StatusCode::NOT_FOUND);
}

TEST_F(BadInputTest, BadSampleAndQueryRequestsAreRejected) {
  {
    Reply<v1::SampleReplayResponse> reply =
        SampleReplay(stub(), kFleet, "robot-1", 0);
    ExpectError("SampleReplay count 0", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"count"});
  }
  {
    Reply<v1::SampleReplayResponse> reply =
        SampleReplay(stub(), kFleet, "robot-1", 10001);
    ExpectError("SampleReplay count 10,001", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"count"});
  }
  {
    Reply<v1::SampleReplayResponse> reply =
        SampleReplay(stub(), "", "robot-1", 1);
    ExpectError("SampleReplay empty fleet", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"fleet_id", "fleet id"});
  }
  std::vector<float> code = CodeOf(NewTrace());
  {
    std::vector<float> short_code(code.begin(), code.end() - 1);
    Reply<v1::QueryPlaceResponse> reply =
        QueryCode(stub(), kFleet, short_code, 5);
    ExpectError("QueryPlace wrong dimension", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"dimension"});
  }
  {
    std::vector<float> nan_code = code;
    nan_code[5] = std::numeric_limits<float>::quiet_NaN();
    Reply<v1::QueryPlaceResponse> reply =
        QueryCode(stub(), kFleet, nan_code, 5);
    ExpectError("QueryPlace NaN", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"finite", "nan"});
  }
  {
    Reply<v1::QueryPlaceResponse> reply = QueryCode(stub(), kFleet, code, 1001);
    ExpectError("QueryPlace k 1,001", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT,
                {"1000", "1,000", " k", "k ", "k=", "k:", "`k`", "'k'"});
  }
  {
    Reply<v1::GetStatsResponse> reply = GetStats(stub(), "");
    ExpectError("GetStats empty fleet", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"fleet_id", "fleet id"});
  }
  {
    Reply<v1::ConsolidateResponse> reply = Consolidate(stub(), "bad fleet!");
    ExpectError("Consolidate malformed fleet", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"fleet_id", "fleet id"});
  }
  {
    Reply<std::vector<v1::MemoryEvent>> reply = ReadEvents(
        stub(), "bad fleet!", 0, 0, SIZE_MAX, std::chrono::seconds(10));
    ExpectError("WatchMemory malformed fleet", reply.status,
                grpc::StatusCode::INVALID_ARGUMENT, {"fleet_id", "fleet id"});
  }
  ASSERT_NO_FATAL_FAILURE(ExpectStatsUnchanged("bad sample/query requests"));
}

TEST_F(BadInputTest, UnknownFleetIsNotFound) {
  const std::string fleet = "no-such-fleet";
  ExpectError("GetStats", GetStats(stub(), fleet).status,
              grpc::StatusCode::NOT_FOUND, {fleet, "fleet"});
  ExpectError("Consolidate", Consolidate(stub(), fleet).status,
              grpc::StatusCode::NOT_FOUND, {fleet, "fleet"});
  ExpectError("SampleReplay", SampleReplay(stub(), fleet, "robot-1", 5).status,
              grpc::StatusCode::NOT_FOUND, {fleet, "fleet"});
  ExpectError("QueryPlace",
              QueryCode(stub(), fleet, CodeOf(NewTrace()), 5).status,
              grpc::StatusCode::NOT_FOUND, {fleet, "fleet"});
  // None of these created it.
  EXPECT_EQ(GetStats(stub(), fleet).status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  ASSERT_NO_FATAL_FAILURE(ExpectStatsUnchanged("calls on an unknown fleet"));
}

TEST_F(BadInputTest, BadMessageKeepsTheEarlierMessagesOfTheStream) {
  // Message 1: ten new traces. Message 2: ten more, one with a NaN.
  std::vector<v1::MemoryTrace> good, bad;
  for (uint64_t seq = 100; seq < 110; ++seq) good.push_back(NewTrace(seq));
  for (uint64_t seq = 110; seq < 120; ++seq) bad.push_back(NewTrace(seq));
  bad[4].set_code(1, std::numeric_limits<float>::quiet_NaN());
  std::vector<v1::UploadTracesRequest> requests = {
      MakeUploadRequest(kFleet, good), MakeUploadRequest(kFleet, bad)};
  Reply<v1::UploadTracesResponse> reply = Upload(stub(), requests);
  ExpectError("second message with NaN", reply.status,
              grpc::StatusCode::INVALID_ARGUMENT, {"finite", "nan"});

  Reply<v1::GetStatsResponse> stats = GetStats(stub(), kFleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), before_.pending_traces() + 10)
      << "the first message is durable, nothing of the second";

  // A retry of the first message finds it; the second (fixed) is new.
  bad[4] = NewTrace(114);
  requests = {MakeUploadRequest(kFleet, good), MakeUploadRequest(kFleet, bad)};
  reply = Upload(stub(), requests);
  ASSERT_TRUE(reply.ok()) << Describe(reply.status);
  EXPECT_EQ(reply.response.duplicates(), 10u);
  EXPECT_EQ(reply.response.accepted(), 10u);
}

TEST_F(BadInputTest, StreamMustNameOneFleet) {
  std::vector<v1::MemoryTrace> first, second;
  for (uint64_t seq = 200; seq < 205; ++seq) first.push_back(NewTrace(seq));
  for (uint64_t seq = 205; seq < 210; ++seq) second.push_back(NewTrace(seq));
  std::vector<v1::UploadTracesRequest> requests = {
      MakeUploadRequest(kFleet, first),
      MakeUploadRequest("fleet-other", second)};
  Reply<v1::UploadTracesResponse> reply = Upload(stub(), requests);
  ExpectError("two fleets in one stream", reply.status,
              grpc::StatusCode::INVALID_ARGUMENT, {"fleet"});
  EXPECT_EQ(GetStats(stub(), "fleet-other").status.error_code(),
            grpc::StatusCode::NOT_FOUND);
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), kFleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), before_.pending_traces() + 5);
}

class DeadlineTest : public ServerTest {};

TEST_F(DeadlineTest, ExpiredDeadlinesEndCallsWithDeadlineExceeded) {
  TraceSpec spec{.robot_id = "robot-d", .count = 60, .dimension = kDim};
  std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
  ASSERT_TRUE(UploadTraces(stub(), "fleet-deadline", traces).ok());
  // A deadline that has already passed when the call starts (gRPC rounds
  // deadlines up to whole milliseconds, so "now + 1 us" may still succeed on
  // loopback).
  auto expired_context = [] {
    auto context = std::make_unique<grpc::ClientContext>();
    context->set_deadline(std::chrono::system_clock::now() -
                          std::chrono::milliseconds(1));
    return context;
  };
  {
    v1::GetStatsRequest request;
    request.set_fleet_id("fleet-deadline");
    v1::GetStatsResponse response;
    auto context = expired_context();
    EXPECT_EQ(stub().GetStats(context.get(), request, &response).error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    v1::ConsolidateRequest request;
    request.set_fleet_id("fleet-deadline");
    v1::ConsolidateResponse response;
    auto context = expired_context();
    EXPECT_EQ(
        stub().Consolidate(context.get(), request, &response).error_code(),
        grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    v1::QueryPlaceRequest request;
    request.set_fleet_id("fleet-deadline");
    for (float value : CodeOf(traces[0])) request.add_code(value);
    v1::QueryPlaceResponse response;
    auto context = expired_context();
    EXPECT_EQ(stub().QueryPlace(context.get(), request, &response).error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    v1::SampleReplayRequest request;
    request.set_fleet_id("fleet-deadline");
    request.set_robot_id("robot-d");
    request.set_count(10);
    v1::SampleReplayResponse response;
    auto context = expired_context();
    EXPECT_EQ(
        stub().SampleReplay(context.get(), request, &response).error_code(),
        grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    v1::UploadTracesResponse response;
    auto context = expired_context();
    auto writer = stub().UploadTraces(context.get(), &response);
    writer->Write(MakeUploadRequest("fleet-deadline", traces));
    writer->WritesDone();
    EXPECT_EQ(writer->Finish().error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  {
    v1::WatchMemoryRequest request;
    request.set_fleet_id("fleet-deadline");
    auto context = expired_context();
    auto reader = stub().WatchMemory(context.get(), request);
    v1::MemoryEvent event;
    while (reader->Read(&event)) {
    }
    EXPECT_EQ(reader->Finish().error_code(),
              grpc::StatusCode::DEADLINE_EXCEEDED);
  }
  // The server is fine afterwards, and the fleet consistent: either the
  // consolidation ran (60 traces on a 300 m route into 20 clusters: nothing
  // to downsample) or it did not.
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), "fleet-deadline");
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.traces() + stats.response.pending_traces(), 60u);
  const v1::RobotStats* robot = FindRobot(stats.response, "robot-d");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->received(), 60u);
}

TEST_F(DeadlineTest, IdleWatchEndsAtItsDeadlineAfterTheHistory) {
  TraceSpec spec{.robot_id = "robot-d", .count = 40, .dimension = kDim};
  ASSERT_TRUE(UploadTraces(stub(), "fleet-idle", MakeTraces(spec)).ok());
  Reply<v1::ConsolidateResponse> consolidated =
      Consolidate(stub(), "fleet-idle");
  ASSERT_TRUE(consolidated.ok()) << Describe(consolidated.status);
  // No limits: reads until the call's 1 s deadline ends it.
  Reply<std::vector<v1::MemoryEvent>> events =
      ReadEvents(stub(), "fleet-idle", 0, 0, SIZE_MAX, std::chrono::seconds(1));
  EXPECT_EQ(events.status.error_code(), grpc::StatusCode::DEADLINE_EXCEEDED)
      << Describe(events.status);
  EXPECT_EQ(events.response.size(), consolidated.response.clusters_added());
}

TEST_F(DeadlineTest, UnfinishedUploadStreamEndsAtItsDeadline) {
  TraceSpec spec{.robot_id = "robot-d", .count = 10, .dimension = kDim};
  std::vector<v1::MemoryTrace> traces = MakeTraces(spec);
  // One message and then nothing (the client never closes the stream).
  v1::UploadTracesResponse response;
  auto context = MakeContext(std::chrono::seconds(1));
  auto writer = stub().UploadTraces(context.get(), &response);
  ASSERT_TRUE(writer->Write(MakeUploadRequest("fleet-open", traces)));
  EXPECT_EQ(writer->Finish().error_code(), grpc::StatusCode::DEADLINE_EXCEEDED);
  // The message was stored whole or not at all, and the server still works.
  Reply<v1::GetStatsResponse> stats = GetStats(stub(), "fleet-open");
  if (stats.status.error_code() == grpc::StatusCode::NOT_FOUND) return;
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), 10u);
}

class StandardServicesTest : public ServerTest {};

TEST_F(StandardServicesTest, HealthCheckIsServing) {
  std::shared_ptr<grpc::Channel> channel = MakeChannel(server().address());
  // grpc.health.v1.HealthCheckRequest{service: ""} is the empty message;
  // HealthCheckResponse{status: SERVING} is field 1 = 1: bytes 08 01.
  std::string response;
  grpc::Status status = GenericUnaryCall(
      channel.get(), "/grpc.health.v1.Health/Check", "", &response);
  ASSERT_TRUE(status.ok()) << Describe(status);
  EXPECT_EQ(response, std::string("\x08\x01", 2)) << "status is not SERVING";
}

// Issue 32: gRPC's generated handler answered UNIMPLEMENTED with no message.
TEST_F(BadInputTest, UnparseableUnaryRequestIsInvalidArgument) {
  std::shared_ptr<grpc::Channel> channel = MakeChannel(server().address());
  for (const char* method : {"GetStats", "QueryPlace", "SampleReplay"}) {
    std::string response;
    grpc::Status status = GenericUnaryCall(
        channel.get(), absl::StrCat("/fleetmem.v1.MemoryService/", method),
        std::string("\x0a\xff\xff\xff\x0f", 5), &response);
    ExpectError(method, status, grpc::StatusCode::INVALID_ARGUMENT,
                {"do not parse"});
  }
  // The watch too (issue 44: it answered UNIMPLEMENTED).
  std::string response;
  const grpc::Status watch =
      GenericStreamCall(channel, "/fleetmem.v1.MemoryService/WatchMemory",
                        {std::string("\x0a\xff\xff\xff\x0f", 5)}, &response);
  ExpectError("WatchMemory", watch, grpc::StatusCode::INVALID_ARGUMENT,
              {"do not parse"});
  ExpectStatsUnchanged("unparseable requests");
}

// Issue 32: after_event = 2^64 - 1 was answered OUT_OF_RANGE "events 0..0
// erased". No event comes after it: nothing is read, and a watch waits.
TEST_F(BadInputTest, TheLargestCursorReadsNoEvents) {
  constexpr uint64_t kLast = std::numeric_limits<uint64_t>::max();
  v1::ListEventsRequest request;
  request.set_fleet_id(kFleet);
  request.set_after(kLast);
  v1::ListEventsResponse listed;
  auto context = MakeContext();
  grpc::Status status = stub().ListEvents(context.get(), request, &listed);
  ASSERT_TRUE(status.ok()) << Describe(status);
  EXPECT_EQ(listed.events_size(), 0);
  EXPECT_EQ(listed.last_event_id(), kLast);
  Reply<std::vector<v1::MemoryEvent>> watched = ReadEvents(
      stub(), kFleet, kLast, 0, SIZE_MAX, std::chrono::milliseconds(500));
  EXPECT_EQ(watched.status.error_code(), grpc::StatusCode::DEADLINE_EXCEEDED)
      << Describe(watched.status);
  EXPECT_TRUE(watched.response.empty());
}

TEST_F(BadInputTest, UnparseableUploadMessageFailsTheStream) {
  // Message 1: ten good traces; message 2: bytes that are no
  // UploadTracesRequest; message 3: ten more good traces.
  std::vector<v1::MemoryTrace> first, third;
  for (uint64_t seq = 301; seq <= 310; ++seq) first.push_back(NewTrace(seq));
  for (uint64_t seq = 311; seq <= 320; ++seq) third.push_back(NewTrace(seq));
  const std::vector<std::string> messages = {
      MakeUploadRequest(kFleet, first).SerializeAsString(),
      std::string("\x12\xff\xff\xff\x0f garbage", 13),
      MakeUploadRequest(kFleet, third).SerializeAsString()};
  std::string response;
  grpc::Status status = GenericStreamCall(
      MakeChannel(server().address()),
      "/fleetmem.v1.MemoryService/UploadTraces", messages, &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
      << Describe(status);
  for (const char* words : {"message 2 of the stream", "do not parse",
                            "messages 1..1 are durable (10 accepted"}) {
    EXPECT_TRUE(absl::StrContains(status.error_message(), words))
        << status.error_message();
  }
  // The stream's uploads are acknowledged as durable: applied a moment later.
  Reply<v1::GetStatsResponse> stats = GetStatsApplied(stub(), kFleet);
  ASSERT_TRUE(stats.ok()) << Describe(stats.status);
  EXPECT_EQ(stats.response.pending_traces(), before_.pending_traces() + 10)
      << "message 1 is durable; the call failed before message 3";
}

// Both versions (issue 48: gRPC 1.51's library serves only v1alpha; the
// server adds v1, which newer tools ask first).
TEST_F(StandardServicesTest, ReflectionListsTheMemoryService) {
  std::shared_ptr<grpc::Channel> channel = MakeChannel(server().address());
  for (const char* method :
       {"/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
        "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"}) {
    std::string response;
    grpc::Status status = ListServicesByReflection(channel, method, &response);
    ASSERT_TRUE(status.ok()) << method << ": " << Describe(status);
    EXPECT_TRUE(absl::StrContains(response, "fleetmem.v1.MemoryService"))
        << method << " does not list fleetmem.v1.MemoryService";
    EXPECT_TRUE(absl::StrContains(response, "grpc.health.v1.Health"))
        << method << " does not list the health service";
  }
}

// grpcurl ... grpc.health.v1.Health/Check without -proto: reflection must
// describe the health service, not only list it.
TEST_F(StandardServicesTest, ReflectionDescribesTheHealthService) {
  const std::string symbol = "grpc.health.v1.Health";
  // ServerReflectionRequest{file_containing_symbol: symbol}: field 4.
  const std::string request =
      std::string("\x22") + static_cast<char>(symbol.size()) + symbol;
  std::string response;
  grpc::Status status = GenericStreamCall(
      MakeChannel(server().address()),
      "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
      {request}, &response);
  ASSERT_TRUE(status.ok()) << Describe(status);
  EXPECT_TRUE(absl::StrContains(response, "grpc/health/v1/health.proto"))
      << "reflection cannot describe " << symbol << ": " << response;
}

}  // namespace
}  // namespace fleetmem::testing
