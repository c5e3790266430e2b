#include "services/transport/proto_convert.h"

#include <string>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::transport {
namespace {

core::MemoryTrace SampleTrace() {
  core::MemoryTrace trace;
  trace.robot_id = "robot-7";
  trace.seq = 123456789012ULL;
  trace.domain = "winter";
  trace.code = {0.5f, -1.25f, 3.0f, 0.0f};
  trace.place = core::Place{.x = 1.5, .y = -2.25, .z = 0.125, .yaw = 3.0};
  trace.reward = 0.75f;
  trace.reward_external = 0.5f;
  trace.reward_internal = 0.25f;
  trace.timestamp_ns = 1700000000123456789LL;
  trace.replay_count = 4;
  trace.encoder_version = "netvlad-2";
  trace.cluster_id = 99;
  return trace;
}

void ExpectSameTrace(const core::MemoryTrace& a, const core::MemoryTrace& b) {
  EXPECT_EQ(a.robot_id, b.robot_id);
  EXPECT_EQ(a.seq, b.seq);
  EXPECT_EQ(a.domain, b.domain);
  EXPECT_EQ(a.code, b.code);
  EXPECT_EQ(a.place.x, b.place.x);
  EXPECT_EQ(a.place.y, b.place.y);
  EXPECT_EQ(a.place.z, b.place.z);
  EXPECT_EQ(a.place.yaw, b.place.yaw);
  EXPECT_EQ(a.reward, b.reward);
  EXPECT_EQ(a.reward_external, b.reward_external);
  EXPECT_EQ(a.reward_internal, b.reward_internal);
  EXPECT_EQ(a.timestamp_ns, b.timestamp_ns);
  EXPECT_EQ(a.replay_count, b.replay_count);
  EXPECT_EQ(a.encoder_version, b.encoder_version);
  EXPECT_EQ(a.cluster_id, b.cluster_id);
}

TEST(ProtoConvertTest, TraceRoundTrip) {
  core::MemoryTrace trace = SampleTrace();
  v1::MemoryTrace proto;
  TraceToProto(trace, &proto);
  EXPECT_EQ(proto.robot_id(), "robot-7");
  EXPECT_EQ(proto.code_size(), 4);
  EXPECT_EQ(proto.pose().y(), -2.25);
  EXPECT_EQ(proto.cluster_id(), 99u);
  ExpectSameTrace(TraceFromProto(proto), trace);
}

TEST(ProtoConvertTest, TraceToProtoOverwritesCode) {
  v1::MemoryTrace proto;
  proto.add_code(9.0f);
  proto.add_code(9.0f);
  proto.add_code(9.0f);
  proto.add_code(9.0f);
  proto.add_code(9.0f);
  TraceToProto(SampleTrace(), &proto);
  EXPECT_EQ(proto.code_size(), 4);
}

// An import's columns come back as the traces they were made from (but
// for replay_count and cluster_id, which an import does not carry); a
// column of another length, or replay counts given, is refused naming it.
TEST(ProtoConvertTest, ImportedColumnsRoundTripAndBadOnesAreNamed) {
  core::MemoryTrace trace = SampleTrace();
  core::MemoryTrace other = SampleTrace();
  other.seq += 1;
  other.code = {1.0f, 2.0f, 3.0f, 4.0f};
  v1::TraceColumns columns;
  TraceColumnsToProto(std::vector<core::MemoryTrace>{trace, other}, &columns);
  columns.clear_replay_counts();
  columns.clear_cluster_ids();
  absl::StatusOr<std::vector<core::MemoryTrace>> imported =
      ImportedTracesFromColumns(columns);
  ASSERT_TRUE(imported.ok()) << imported.status();
  ASSERT_EQ(imported->size(), 2u);
  trace.replay_count = other.replay_count = 0;
  trace.cluster_id = other.cluster_id = 0;
  ExpectSameTrace((*imported)[0], trace);
  ExpectSameTrace((*imported)[1], other);

  v1::TraceColumns short_places = columns;
  short_places.mutable_places()->RemoveLast();
  absl::Status refused = ImportedTracesFromColumns(short_places).status();
  EXPECT_EQ(refused.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(refused.message()).find("traces.places: 7 values"),
            std::string::npos)
      << refused;
  v1::TraceColumns replayed = columns;
  replayed.add_replay_counts(1);
  replayed.add_replay_counts(2);
  refused = ImportedTracesFromColumns(replayed).status();
  EXPECT_NE(std::string(refused.message()).find("replay_counts"),
            std::string::npos)
      << refused;
  v1::TraceColumns short_codes = columns;
  short_codes.mutable_codes()->pop_back();
  refused = ImportedTracesFromColumns(short_codes).status();
  EXPECT_NE(std::string(refused.message()).find("traces.codes: 31 values"),
            std::string::npos)
      << refused;
}

// A fleet's graph codes: unset is the server's; set, they come back as
// set, and an UpdateFleet naming other codes is refused as a fixed field.
TEST(ProtoConvertTest, GraphCodesRoundTripAndAreFixed) {
  v1::FleetSettings settings;
  EXPECT_EQ(IndexFromProto(settings).hnsw_codes,
            engine::IndexSettings::Codes::kServer);
  settings.set_hnsw_codes(v1::HNSW_CODES_FLOAT);
  engine::FleetInfo info;
  info.settings.index = IndexFromProto(settings);
  EXPECT_EQ(info.settings.index.hnsw_codes,
            engine::IndexSettings::Codes::kFloat);
  v1::FleetSettings back;
  FleetSettingsToProto(info, &back);
  EXPECT_EQ(back.hnsw_codes(), v1::HNSW_CODES_FLOAT);
  v1::FleetSettings update;
  update.set_hnsw_codes(v1::HNSW_CODES_FLOAT);
  EXPECT_TRUE(FleetUpdateFromProto(update, info).ok());
  update.set_hnsw_codes(v1::HNSW_CODES_INT8);
  EXPECT_EQ(FleetUpdateFromProto(update, info).status().code(),
            absl::StatusCode::kFailedPrecondition);
}

TEST(ProtoConvertTest, PlaceRoundTrip) {
  core::Place place{.x = -1e6, .y = 2.5, .z = -0.0, .yaw = -3.14};
  v1::Pose pose;
  PlaceToProto(place, &pose);
  core::Place back = PlaceFromProto(pose);
  EXPECT_EQ(back.x, place.x);
  EXPECT_EQ(back.y, place.y);
  EXPECT_EQ(back.z, place.z);
  EXPECT_EQ(back.yaw, place.yaw);
}

TEST(ProtoConvertTest, UploadIgnoresServerSetFields) {
  v1::UploadTracesRequest request;
  TraceToProto(SampleTrace(), request.add_traces());
  core::MemoryTrace second = SampleTrace();
  second.seq = 2;
  TraceToProto(second, request.add_traces());

  std::vector<core::MemoryTrace> traces =
      UploadedTracesFromProto(request.traces());
  ASSERT_EQ(traces.size(), 2u);
  EXPECT_EQ(traces[0].replay_count, 0u);
  EXPECT_EQ(traces[0].cluster_id, 0u);
  EXPECT_EQ(traces[0].seq, 123456789012ULL);
  EXPECT_EQ(traces[1].seq, 2u);
  EXPECT_EQ(traces[1].code, SampleTrace().code);
}

TEST(ProtoConvertTest, EventToProto) {
  struct Case {
    core::EventType type;
    v1::MemoryEvent::Type want;
  };
  const Case cases[] = {
      {core::EventType::kClusterAdded, v1::MemoryEvent::CLUSTER_ADDED},
      {core::EventType::kClusterForgotten, v1::MemoryEvent::CLUSTER_FORGOTTEN},
      {core::EventType::kClusterMerged, v1::MemoryEvent::CLUSTER_MERGED},
  };
  for (const Case& c : cases) {
    core::MemoryEvent event;
    event.id = 17;
    event.type = c.type;
    event.cluster_id = 5;
    event.trace_count = 42;
    event.robot_id = "r1";
    event.domain = "night";
    event.centroid_place = core::Place{.x = 1, .y = 2, .z = 3, .yaw = 0};
    event.mean_reward = 0.5f;
    event.timestamp_ns = 77;
    event.merged_into = 9;
    event.traces_dropped = 4;
    v1::MemoryEvent proto;
    EventToProto(event, &proto);
    EXPECT_EQ(proto.id(), 17u);
    EXPECT_EQ(proto.type(), c.want);
    EXPECT_EQ(proto.cluster_id(), 5u);
    EXPECT_EQ(proto.trace_count(), 42u);
    EXPECT_EQ(proto.robot_id(), "r1");
    EXPECT_EQ(proto.domain(), "night");
    EXPECT_EQ(proto.centroid_pose().z(), 3.0);
    EXPECT_EQ(proto.mean_reward(), 0.5f);
    EXPECT_EQ(proto.timestamp_ns(), 77);
    EXPECT_EQ(proto.merged_into(), 9u);
    EXPECT_EQ(proto.traces_dropped(), 4u);
  }
}

TEST(ProtoConvertTest, QueryFromProto) {
  v1::QueryPlaceRequest request;
  request.set_fleet_id("f");
  request.add_code(1.0f);
  request.add_code(2.0f);
  request.set_k(7);
  request.mutable_near()->set_x(10.0);
  request.set_radius_m(25.0);
  engine::PlaceQuery query = QueryFromProto(request);
  EXPECT_EQ(query.code, (std::vector<float>{1.0f, 2.0f}));
  EXPECT_EQ(query.k, 7u);
  EXPECT_EQ(query.near.x, 10.0);
  EXPECT_EQ(query.radius_m, 25.0);
}

TEST(ProtoConvertTest, UploadResultsAddUp) {
  v1::UploadTracesResponse response;
  AddUploadResult({.accepted = 3, .duplicates = 1, .consolidations = 0},
                  &response);
  AddUploadResult({.accepted = 5, .duplicates = 2, .consolidations = 1},
                  &response);
  EXPECT_EQ(response.accepted(), 8u);
  EXPECT_EQ(response.duplicates(), 3u);
  EXPECT_EQ(response.consolidations(), 1u);
}

TEST(ProtoConvertTest, ConsolidateResult) {
  v1::ConsolidateResponse response;
  ConsolidateResultToProto({.consolidated_traces = 1,
                            .downsampled_traces = 2,
                            .clusters_added = 3,
                            .clusters_forgotten = 4,
                            .clusters = 5,
                            .traces = 6},
                           &response);
  EXPECT_EQ(response.consolidated_traces(), 1u);
  EXPECT_EQ(response.downsampled_traces(), 2u);
  EXPECT_EQ(response.clusters_added(), 3u);
  EXPECT_EQ(response.clusters_forgotten(), 4u);
  EXPECT_EQ(response.clusters(), 5u);
  EXPECT_EQ(response.traces(), 6u);
}

TEST(ProtoConvertTest, MatchesAndSamples) {
  std::vector<engine::PlaceMatch> matches = {{SampleTrace(), 0.25f},
                                             {SampleTrace(), 0.5f}};
  matches[1].trace.seq = 8;
  v1::QueryPlaceResponse query_response;
  MatchesToProto(matches, &query_response);
  ASSERT_EQ(query_response.matches_size(), 2);
  EXPECT_EQ(query_response.matches(0).distance(), 0.25f);
  EXPECT_EQ(query_response.matches(1).trace().seq(), 8u);
  ExpectSameTrace(TraceFromProto(query_response.matches(0).trace()),
                  SampleTrace());

  std::vector<core::MemoryTrace> sampled = {SampleTrace()};
  v1::SampleReplayResponse sample_response;
  SampledTracesToProto(sampled, &sample_response);
  ASSERT_EQ(sample_response.traces_size(), 1);
  EXPECT_EQ(sample_response.traces(0).replay_count(), 4u);
}

TEST(ProtoConvertTest, Stats) {
  engine::FleetStats stats;
  stats.traces = 10;
  stats.pending_traces = 3;
  stats.clusters = 2;
  stats.code_dimension = 256;
  stats.encoder_version = "v9";
  stats.last_event_id = 12;
  stats.consolidations = 4;
  stats.clusters_forgotten = 1;
  stats.max_clusters = 100;
  stats.max_traces_per_cluster = 50;
  stats.robots = {{.robot_id = "a",
                   .traces = 6,
                   .pending_traces = 1,
                   .max_seq = 9,
                   .received = 7,
                   .replayed = 11},
                  {.robot_id = "b", .traces = 4}};
  stats.domains = {{.domain = "summer", .traces = 10, .pending_traces = 3}};
  v1::GetStatsResponse out;
  StatsToProto(stats, &out);
  EXPECT_EQ(out.traces(), 10u);
  EXPECT_EQ(out.pending_traces(), 3u);
  EXPECT_EQ(out.clusters(), 2u);
  EXPECT_EQ(out.code_dimension(), 256u);
  EXPECT_EQ(out.encoder_version(), "v9");
  EXPECT_EQ(out.last_event_id(), 12u);
  EXPECT_EQ(out.consolidations(), 4u);
  EXPECT_EQ(out.clusters_forgotten(), 1u);
  EXPECT_EQ(out.max_clusters(), 100u);
  EXPECT_EQ(out.max_traces_per_cluster(), 50u);
  ASSERT_EQ(out.robots_size(), 2);
  EXPECT_EQ(out.robots(0).robot_id(), "a");
  EXPECT_EQ(out.robots(0).max_seq(), 9u);
  EXPECT_EQ(out.robots(0).received(), 7u);
  EXPECT_EQ(out.robots(0).replayed(), 11u);
  EXPECT_EQ(out.robots(0).pending_traces(), 1u);
  EXPECT_EQ(out.robots(1).traces(), 4u);
  ASSERT_EQ(out.domains_size(), 1);
  EXPECT_EQ(out.domains(0).domain(), "summer");
  EXPECT_EQ(out.domains(0).pending_traces(), 3u);
}

}  // namespace
}  // namespace fleetmem::transport
