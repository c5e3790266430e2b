// The service over an in-process channel, with a real engine on the
// in-memory store and the exact index.
#include "services/transport/memory_service.h"

#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "absl/synchronization/notification.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "gmock/gmock.h"
#include "grpcpp/grpcpp.h"
#include "gtest/gtest.h"
#include "services/index/exact_index.h"
#include "services/storage/in_memory_log.h"
#include "services/storage/in_memory_store.h"
#include "services/transport/embedded_memory.h"

namespace fleetmem::transport {
namespace {

constexpr size_t kDimension = 4;

v1::MemoryTrace Trace(const std::string& robot, uint64_t seq) {
  v1::MemoryTrace trace;
  trace.set_robot_id(robot);
  trace.set_seq(seq);
  trace.set_domain("summer");
  for (size_t i = 0; i < kDimension; ++i) {
    trace.add_code(static_cast<float>((seq * 7 + i * 3) % 11) - 5.0f);
  }
  trace.mutable_pose()->set_x(static_cast<double>(seq));
  trace.set_reward(0.5f);
  trace.set_encoder_version("enc");
  trace.set_replay_count(77);  // ignored on upload
  return trace;
}

v1::UploadTracesRequest Batch(const std::string& fleet, uint64_t first,
                              uint64_t count) {
  v1::UploadTracesRequest request;
  request.set_fleet_id(fleet);
  // Applied before the answer: these tests read what they uploaded.
  request.set_ack(v1::UPLOAD_ACK_APPLIED);
  for (uint64_t seq = first; seq < first + count; ++seq) {
    *request.add_traces() = Trace("r1", seq);
  }
  return request;
}

class MemoryServiceTest : public ::testing::Test {
 protected:
  void Start(WorkQueueOptions work_options) {
    store_ = storage::NewInMemoryStore();
    engine::EngineOptions options;
    options.segment_size = 10;
    options.memory.clusters_per_batch = 2;
    options.max_events_per_read = 3;  // watches read several pages
    auto engine = engine::MemoryEngine::Open(
        options, store_.get(),
        [](size_t dimension) { return index::NewExactIndex(dimension); });
    ASSERT_TRUE(engine.ok()) << engine.status();
    engine_ = std::move(*engine);
    auto memory = EmbeddedMemory::Open(engine_.get(), log_.get());
    ASSERT_TRUE(memory.ok()) << memory.status();
    memory_ = std::move(*memory);
    work_ = std::make_unique<WorkQueue>(work_options);
    service_ = std::make_unique<MemoryServiceImpl>(engine_.get(), memory_.get(),
                                                   work_.get());
    grpc::ServerBuilder builder;
    builder.RegisterService(service_.get());
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);
    stub_ = v1::MemoryService::NewStub(
        server_->InProcessChannel(grpc::ChannelArguments()));
  }

  void SetUp() override { Start({.threads = 2, .max_queued = 64}); }

  void TearDown() override {
    service_->Shutdown();
    server_->Shutdown(std::chrono::system_clock::now() +
                      std::chrono::seconds(5));
    work_->Stop();
    memory_.reset();
  }

  grpc::Status Upload(const std::vector<v1::UploadTracesRequest>& messages,
                      v1::UploadTracesResponse* response) {
    grpc::ClientContext context;
    auto writer = stub_->UploadTraces(&context, response);
    for (const v1::UploadTracesRequest& message : messages) {
      if (!writer->Write(message)) break;
    }
    writer->WritesDone();
    return writer->Finish();
  }

  grpc::Status Stats(const std::string& fleet, v1::GetStatsResponse* out) {
    grpc::ClientContext context;
    v1::GetStatsRequest request;
    request.set_fleet_id(fleet);
    return stub_->GetStats(&context, request, out);
  }

  std::unique_ptr<engine::MemoryStore> store_;
  std::unique_ptr<engine::FleetLog> log_ = storage::NewInMemoryLog();
  std::unique_ptr<engine::MemoryEngine> engine_;
  std::unique_ptr<EmbeddedMemory> memory_;
  std::unique_ptr<WorkQueue> work_;
  std::unique_ptr<MemoryServiceImpl> service_;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<v1::MemoryService::Stub> stub_;
};

TEST_F(MemoryServiceTest, ADurableAckAnswersBeforeApplyingAndSaysWhere) {
  v1::UploadTracesRequest first = Batch("f", 0, 6);
  first.set_ack(v1::UPLOAD_ACK_UNSPECIFIED);  // the default: durable
  v1::UploadTracesRequest second = Batch("f", 6, 6);
  second.set_ack(v1::UPLOAD_ACK_DURABLE);
  v1::UploadTracesResponse response;
  ASSERT_TRUE(Upload({first, second}, &response).ok());
  EXPECT_EQ(response.accepted(), 12u);
  EXPECT_EQ(response.consolidations(), 0u);  // counted only when applied
  EXPECT_FALSE(response.applied());
  EXPECT_EQ(response.last_sequence(), 2u);  // one log entry per message
  // Applied behind the answer: stats say how far.
  ASSERT_TRUE(
      memory_->writes()
          .WaitApplied("f", response.last_sequence(), absl::InfiniteFuture())
          .ok());
  v1::GetStatsResponse stats;
  ASSERT_TRUE(Stats("f", &stats).ok());
  EXPECT_EQ(stats.acknowledged_through(), 2u);
  EXPECT_EQ(stats.applied_through(), 2u);
  EXPECT_EQ(stats.backlog_traces(), 0u);
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 12u);
  EXPECT_EQ(stats.consolidations(), 1u);  // segment_size 10 reached

  // A resent message is a duplicate at the append: nothing new in the log.
  v1::UploadTracesResponse again;
  ASSERT_TRUE(Upload({second}, &again).ok());
  EXPECT_EQ(again.accepted(), 0u);
  EXPECT_EQ(again.duplicates(), 6u);
  EXPECT_EQ(again.last_sequence(), 0u);
}

TEST_F(MemoryServiceTest, UploadSumsMessagesAndCountsDuplicates) {
  v1::UploadTracesResponse response;
  ASSERT_TRUE(Upload({Batch("f", 0, 6), Batch("f", 6, 6)}, &response).ok());
  EXPECT_EQ(response.accepted(), 12u);
  EXPECT_EQ(response.duplicates(), 0u);
  EXPECT_EQ(response.consolidations(), 1u);  // segment_size 10 reached
  EXPECT_TRUE(response.applied());

  v1::UploadTracesResponse again;
  ASSERT_TRUE(Upload({Batch("f", 10, 4)}, &again).ok());
  EXPECT_EQ(again.accepted(), 2u);
  EXPECT_EQ(again.duplicates(), 2u);

  v1::GetStatsResponse stats;
  ASSERT_TRUE(Stats("f", &stats).ok());
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 14u);
  EXPECT_EQ(stats.code_dimension(), kDimension);
}

TEST_F(MemoryServiceTest, UploadStreamMustNameOneFleet) {
  v1::UploadTracesResponse response;
  grpc::Status status = Upload({Batch("f", 0, 2), Batch("g", 2, 2)}, &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_NE(status.error_message().find("same fleet"), std::string::npos);
  // The first message is durable.
  v1::GetStatsResponse stats;
  ASSERT_TRUE(Stats("f", &stats).ok());
  EXPECT_EQ(stats.pending_traces(), 2u);
  EXPECT_EQ(Stats("g", &stats).error_code(), grpc::StatusCode::NOT_FOUND);
}

// The messages of one stream are read while earlier ones are written, and
// written together: each stays its own log entry, and a refusal names its
// message and what the others did.
TEST_F(MemoryServiceTest, AStreamsMessagesAreWrittenTogetherInOrder) {
  std::vector<v1::UploadTracesRequest> messages;
  for (int m = 0; m < 40; ++m) {
    messages.push_back(Batch("f", static_cast<uint64_t>(m) * 5, 5));
    messages.back().set_ack(v1::UPLOAD_ACK_DURABLE);
  }
  v1::UploadTracesResponse response;
  ASSERT_TRUE(Upload(messages, &response).ok());
  EXPECT_EQ(response.accepted(), 200u);
  EXPECT_EQ(response.last_sequence(), 40u);
  ASSERT_TRUE(
      memory_->writes().WaitApplied("f", 40, absl::InfiniteFuture()).ok());
  v1::GetStatsResponse stats;
  ASSERT_TRUE(Stats("f", &stats).ok());
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 200u);

  // Message 25 of the next stream is refused.
  messages.clear();
  for (int m = 0; m < 40; ++m) {
    messages.push_back(Batch("f", 1000 + static_cast<uint64_t>(m) * 5, 5));
    messages.back().set_ack(v1::UPLOAD_ACK_DURABLE);
  }
  messages[24].mutable_traces(2)->set_robot_id("");
  grpc::Status status = Upload(messages, &response);
  ASSERT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(),
              ::testing::HasSubstr("message 25 of the stream: "));
  EXPECT_THAT(status.error_message(),
              ::testing::HasSubstr("messages 1..24 are durable (120 accepted"));
  // Messages after it written in the same store write are said to be.
  uint64_t later = 0;
  const size_t said = status.error_message().find(" messages after it were");
  if (said != std::string::npos) {
    const size_t begin = status.error_message().rfind("; ", said) + 2;
    later = std::stoull(status.error_message().substr(begin, said - begin));
  }
  ASSERT_TRUE(
      memory_->writes().WaitAppliedAll("f", absl::InfiniteFuture()).ok());
  ASSERT_TRUE(Stats("f", &stats).ok());
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 200u + 120u + 5 * later);
}

TEST_F(MemoryServiceTest, EngineErrorsKeepTheirCode) {
  v1::UploadTracesRequest bad = Batch("f", 0, 1);
  bad.mutable_traces(0)->set_robot_id("");
  v1::UploadTracesResponse response;
  EXPECT_EQ(Upload({bad}, &response).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);

  v1::GetStatsResponse stats;
  EXPECT_EQ(Stats("nobody", &stats).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_EQ(Stats("bad fleet", &stats).error_code(),
            grpc::StatusCode::INVALID_ARGUMENT);
}

TEST_F(MemoryServiceTest, UnaryCalls) {
  v1::UploadTracesResponse uploaded;
  ASSERT_TRUE(Upload({Batch("f", 0, 8)}, &uploaded).ok());
  {
    grpc::ClientContext context;
    v1::ConsolidateRequest request;
    request.set_fleet_id("f");
    v1::ConsolidateResponse response;
    ASSERT_TRUE(stub_->Consolidate(&context, request, &response).ok());
    EXPECT_EQ(response.consolidated_traces(), 8u);
    EXPECT_EQ(response.traces(), 8u);
  }
  {
    grpc::ClientContext context;
    v1::SampleReplayRequest request;
    request.set_fleet_id("f");
    request.set_robot_id("r2");
    request.set_count(3);
    v1::SampleReplayResponse response;
    ASSERT_TRUE(stub_->SampleReplay(&context, request, &response).ok());
    ASSERT_EQ(response.traces_size(), 3);
    EXPECT_EQ(response.traces(0).replay_count(), 1u);  // not the uploaded 77
    EXPECT_NE(response.traces(0).cluster_id(), 0u);
  }
  {
    grpc::ClientContext context;
    v1::QueryPlaceRequest request;
    request.set_fleet_id("f");
    *request.mutable_code() = Trace("r1", 5).code();
    request.set_k(2);
    v1::QueryPlaceResponse response;
    ASSERT_TRUE(stub_->QueryPlace(&context, request, &response).ok());
    ASSERT_EQ(response.matches_size(), 2);
    EXPECT_EQ(response.matches(0).distance(), 0.0f);
  }
}

// Reads events until `count` have arrived; false if the stream ended first.
bool ReadEvents(grpc::ClientReaderInterface<v1::MemoryEvent>* reader,
                size_t count, std::vector<v1::MemoryEvent>* out) {
  v1::MemoryEvent event;
  while (out->size() < count) {
    if (!reader->Read(&event)) return false;
    out->push_back(event);
  }
  return true;
}

TEST_F(MemoryServiceTest, WatchStreamsHistoryThenLiveEventsUntilShutdown) {
  v1::UploadTracesResponse uploaded;
  ASSERT_TRUE(Upload({Batch("f", 0, 10)}, &uploaded).ok());  // 2 clusters

  grpc::ClientContext context;
  v1::WatchMemoryRequest request;
  request.set_fleet_id("f");
  auto reader = stub_->WatchMemory(&context, request);
  std::vector<v1::MemoryEvent> events;
  ASSERT_TRUE(ReadEvents(reader.get(), 2, &events));

  // Live: four more segments, more events than one read page (3).
  ASSERT_TRUE(Upload({Batch("f", 10, 10), Batch("f", 20, 10),
                      Batch("f", 30, 10), Batch("f", 40, 10)},
                     &uploaded)
                  .ok());
  EXPECT_EQ(uploaded.consolidations(), 4u);
  ASSERT_TRUE(ReadEvents(reader.get(), 10, &events));
  for (size_t i = 0; i < events.size(); ++i) {
    EXPECT_EQ(events[i].id(), i + 1);
    EXPECT_EQ(events[i].type(), v1::MemoryEvent::CLUSTER_ADDED);
  }

  service_->Shutdown();
  v1::MemoryEvent extra;
  EXPECT_FALSE(reader->Read(&extra));
  EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::UNAVAILABLE);

  // New calls are refused.
  v1::GetStatsResponse stats;
  EXPECT_EQ(Stats("f", &stats).error_code(), grpc::StatusCode::UNAVAILABLE);
  grpc::ClientContext late;
  auto late_reader = stub_->WatchMemory(&late, request);
  EXPECT_FALSE(late_reader->Read(&extra));
  EXPECT_EQ(late_reader->Finish().error_code(), grpc::StatusCode::UNAVAILABLE);
}

TEST_F(MemoryServiceTest, WatchResumesAfterCursor) {
  v1::UploadTracesResponse uploaded;
  ASSERT_TRUE(
      Upload({Batch("f", 0, 10), Batch("f", 10, 10), Batch("f", 20, 10)},
             &uploaded)
          .ok());  // 6 events

  grpc::ClientContext context;
  v1::WatchMemoryRequest request;
  request.set_fleet_id("f");
  request.set_after_event(4);
  auto reader = stub_->WatchMemory(&context, request);
  std::vector<v1::MemoryEvent> events;
  ASSERT_TRUE(ReadEvents(reader.get(), 2, &events));
  EXPECT_EQ(events[0].id(), 5u);
  EXPECT_EQ(events[1].id(), 6u);
  context.TryCancel();
  EXPECT_FALSE(reader->Read(&events.emplace_back()));
  EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::CANCELLED);
}

TEST_F(MemoryServiceTest, WatchRejectsBadFleetId) {
  grpc::ClientContext context;
  v1::WatchMemoryRequest request;
  request.set_fleet_id("no spaces");
  auto reader = stub_->WatchMemory(&context, request);
  v1::MemoryEvent event;
  EXPECT_FALSE(reader->Read(&event));
  EXPECT_EQ(reader->Finish().error_code(), grpc::StatusCode::INVALID_ARGUMENT);
}

// One worker and a queue of one, so that the tests can make the server busy.
class BusyServiceTest : public MemoryServiceTest {
 protected:
  void SetUp() override { Start({.threads = 1, .max_queued = 1}); }
  void TearDown() override {
    if (!release_.HasBeenNotified()) release_.Notify();
    MemoryServiceTest::TearDown();
  }

  // Occupies the only worker until release_ is notified. The notifications
  // are members so that they outlive the worker's use of them.
  void BlockWorker() {
    ASSERT_TRUE(work_->TrySubmit([this] {
      started_.Notify();
      release_.WaitForNotification();
    }));
    started_.WaitForNotification();
  }

  absl::Notification started_;
  absl::Notification release_;
};

TEST_F(BusyServiceTest, FullQueueIsResourceExhausted) {
  BlockWorker();
  ASSERT_TRUE(work_->TrySubmit([] {}));  // the queue is full now

  v1::GetStatsResponse stats;
  grpc::Status status = Stats("f", &stats);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_NE(status.error_message().find("server busy"), std::string::npos);
  v1::UploadTracesResponse uploaded;
  EXPECT_EQ(Upload({Batch("f", 0, 1)}, &uploaded).error_code(),
            grpc::StatusCode::RESOURCE_EXHAUSTED);
}

TEST_F(BusyServiceTest, WorkWhoseDeadlinePassedInTheQueueIsNotDone) {
  BlockWorker();

  // The upload waits behind the blocked worker until its deadline passes.
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::milliseconds(200));
  v1::UploadTracesResponse response;
  auto writer = stub_->UploadTraces(&context, &response);
  writer->Write(Batch("f", 0, 5));
  writer->WritesDone();
  EXPECT_EQ(writer->Finish().error_code(), grpc::StatusCode::DEADLINE_EXCEEDED);
  release_.Notify();
  // Wait until the queued upload task has run (one worker, first in first
  // out): the queue has room for this marker only once the worker took it.
  absl::Notification drained;
  while (!work_->TrySubmit([&drained] { drained.Notify(); })) {
    std::this_thread::yield();
  }
  drained.WaitForNotification();

  v1::GetStatsResponse stats;
  EXPECT_EQ(Stats("f", &stats).error_code(), grpc::StatusCode::NOT_FOUND);
}

// Aliases (engine/fleet_aliases.h): every fleet's call resolves its name
// once; a stream stays on the fleet it started on.
TEST_F(MemoryServiceTest, AnAliasIsResolvedOncePerCallAndStream) {
  v1::UploadTracesResponse uploaded;
  ASSERT_TRUE(Upload({Batch("old", 0, 10)}, &uploaded).ok());
  ASSERT_TRUE(Upload({Batch("new", 100, 10)}, &uploaded).ok());
  auto call = [this](auto method, const auto& request, auto* response) {
    grpc::ClientContext context;
    return (stub_.get()->*method)(&context, request, response);
  };
  v1::CreateAliasRequest create;
  create.set_alias("live");
  create.set_fleet_id("old");
  v1::CreateAliasResponse created;
  ASSERT_TRUE(
      call(&v1::MemoryService::Stub::CreateAlias, create, &created).ok());

  // Refused, nothing changed: an alias of a fleet id, of an alias, of no
  // fleet, twice; a fleet made under an alias's name.
  for (const auto& [alias, fleet, code] :
       std::vector<std::tuple<std::string, std::string, grpc::StatusCode>>{
           {"new", "old", grpc::StatusCode::ALREADY_EXISTS},
           {"other", "live", grpc::StatusCode::INVALID_ARGUMENT},
           {"other", "nope", grpc::StatusCode::NOT_FOUND},
           {"live", "new", grpc::StatusCode::ALREADY_EXISTS}}) {
    create.set_alias(alias);
    create.set_fleet_id(fleet);
    EXPECT_EQ(call(&v1::MemoryService::Stub::CreateAlias, create, &created)
                  .error_code(),
              code)
        << alias << " -> " << fleet;
  }
  v1::CreateFleetRequest make;
  make.set_fleet_id("live");
  make.mutable_settings()->set_code_dimension(kDimension);
  v1::CreateFleetResponse made;
  EXPECT_EQ(
      call(&v1::MemoryService::Stub::CreateFleet, make, &made).error_code(),
      grpc::StatusCode::ALREADY_EXISTS);

  // Reads and writes through the alias reach its fleet.
  v1::GetStatsResponse stats;
  ASSERT_TRUE(Stats("live", &stats).ok());
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 10u);
  v1::QueryPlaceRequest query;
  query.set_fleet_id("live");
  *query.mutable_code() = Trace("r1", 3).code();
  v1::QueryPlaceResponse answer;
  ASSERT_TRUE(call(&v1::MemoryService::Stub::QueryPlace, query, &answer).ok());
  EXPECT_EQ(answer.fleet_id(), "old");
  EXPECT_EQ(answer.encoder_version(), "enc");
  ASSERT_EQ(answer.matches_size(), 1);
  EXPECT_EQ(answer.matches(0).trace().seq(), 3u);

  // A stream opened before a switch stays on its fleet to its end.
  grpc::ClientContext stream_context;
  v1::UploadTracesResponse streamed;
  auto writer = stub_->UploadTraces(&stream_context, &streamed);
  ASSERT_TRUE(writer->Write(Batch("live", 10, 5)));
  // Once the stream's first message is stored (it is bound then).
  for (int i = 0; i < 500; ++i) {
    ASSERT_TRUE(Stats("old", &stats).ok());
    if (stats.traces() + stats.pending_traces() == 15) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  v1::SwitchAliasRequest to_new;
  to_new.set_alias("live");
  to_new.set_fleet_id("new");
  v1::SwitchAliasResponse switched;
  ASSERT_TRUE(
      call(&v1::MemoryService::Stub::SwitchAlias, to_new, &switched).ok());
  EXPECT_EQ(switched.previous_fleet_id(), "old");
  ASSERT_TRUE(writer->Write(Batch("live", 15, 5)));
  writer->WritesDone();
  ASSERT_TRUE(writer->Finish().ok());
  EXPECT_EQ(streamed.accepted(), 10u);
  ASSERT_TRUE(Stats("old", &stats).ok());
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 20u);
  ASSERT_TRUE(Stats("new", &stats).ok());
  EXPECT_EQ(stats.traces() + stats.pending_traces(), 10u);
  ASSERT_TRUE(call(&v1::MemoryService::Stub::QueryPlace, query, &answer).ok());
  EXPECT_EQ(answer.fleet_id(), "new");

  // A query naming codes by encoder takes the fleet's, or says none fits.
  query.clear_code();
  auto* other = query.add_codes_by_encoder();
  other->set_encoder_version("other");
  other->add_code(1.0f);
  EXPECT_EQ(
      call(&v1::MemoryService::Stub::QueryPlace, query, &answer).error_code(),
      grpc::StatusCode::FAILED_PRECONDITION);
  auto* enc = query.add_codes_by_encoder();
  enc->set_encoder_version("enc");
  *enc->mutable_code() = Trace("r1", 104).code();
  ASSERT_TRUE(call(&v1::MemoryService::Stub::QueryPlace, query, &answer).ok());
  ASSERT_EQ(answer.matches_size(), 1);
  EXPECT_EQ(answer.matches(0).trace().seq(), 104u);

  v1::ListAliasesResponse listed;
  ASSERT_TRUE(call(&v1::MemoryService::Stub::ListAliases,
                   v1::ListAliasesRequest(), &listed)
                  .ok());
  ASSERT_EQ(listed.aliases_size(), 1);
  EXPECT_EQ(listed.aliases(0).fleet_id(), "new");
  v1::DeleteAliasRequest drop;
  drop.set_alias("live");
  v1::DeleteAliasResponse dropped;
  ASSERT_TRUE(call(&v1::MemoryService::Stub::DeleteAlias, drop, &dropped).ok());
  EXPECT_EQ(dropped.previous_fleet_id(), "new");
  EXPECT_EQ(Stats("live", &stats).error_code(), grpc::StatusCode::NOT_FOUND);
}

}  // namespace
}  // namespace fleetmem::transport
