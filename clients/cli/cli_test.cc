#include "clients/cli/cli.h"

#include <algorithm>
#include <cmath>
#include <mutex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "clients/cli/flags.h"
#include "clients/cli/printing.h"
#include "clients/cli/synthetic_traces.h"
#include "clients/cli/trace_io.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "gmock/gmock.h"
#include "google/protobuf/util/json_util.h"
#include "grpcpp/grpcpp.h"
#include "gtest/gtest.h"

namespace fleetmem::cli {
namespace {

using ::testing::DoubleEq;
using ::testing::ElementsAre;
using ::testing::FloatEq;
using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::SizeIs;
using ::testing::StartsWith;

// ---------------------------------------------------------------------------
// Flag parsing.

const std::vector<FlagSpec> kGlobal = {{"server", "ADDR", ""},
                                       {"json", "", ""}};
const std::vector<CommandSpec> kSpecs = {
    {"query", "", "", "", {{"fleet", "ID", ""}, {"near", "XYZ", ""}}},
    {"help", "", "", "", {}}};

absl::StatusOr<CommandLine> Parse(std::vector<std::string> args) {
  return ParseCommandLine(args, kGlobal, kSpecs);
}

TEST(ParseCommandLineTest, AcceptsFlagFormsAndGlobalFlagsAnywhere) {
  absl::StatusOr<CommandLine> line = Parse(
      {"--server", "h:1", "query", "--fleet=f", "--near", "-1,2,3", "--json"});
  ASSERT_TRUE(line.ok()) << line.status();
  EXPECT_EQ(line->command, "query");
  EXPECT_EQ(line->global.StringOr("server", ""), "h:1");
  EXPECT_TRUE(line->global.Has("json"));
  EXPECT_EQ(line->flags.StringOr("fleet", ""), "f");
  EXPECT_EQ(line->flags.StringOr("near", ""), "-1,2,3");
  EXPECT_FALSE(line->help);
}

TEST(ParseCommandLineTest, CollectsHelpAndPositionalWords) {
  absl::StatusOr<CommandLine> line = Parse({"help", "query", "-h"});
  ASSERT_TRUE(line.ok()) << line.status();
  EXPECT_EQ(line->command, "help");
  EXPECT_THAT(line->positional, ElementsAre("query"));
  EXPECT_TRUE(line->help);
}

struct BadLineCase {
  std::vector<std::string> args;
  std::string message;
};

class ParseCommandLineErrorTest : public ::testing::TestWithParam<BadLineCase> {
};

TEST_P(ParseCommandLineErrorTest, RejectsWithMessage) {
  absl::StatusOr<CommandLine> line = Parse(GetParam().args);
  ASSERT_FALSE(line.ok());
  EXPECT_EQ(line.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(line.status().message()),
              HasSubstr(GetParam().message));
}

INSTANTIATE_TEST_SUITE_P(
    Cases, ParseCommandLineErrorTest,
    ::testing::Values(
        BadLineCase{{"frobnicate"}, "unknown command 'frobnicate'"},
        BadLineCase{{"query", "--bogus", "1"}, "unknown flag --bogus"},
        BadLineCase{{"--fleet", "f", "query"}, "unknown flag --fleet"},
        BadLineCase{{"query", "--fleet"}, "--fleet needs a value"},
        BadLineCase{{"query", "--json=yes"}, "--json takes no value"}));

TEST(FlagValuesTest, ConvertsAndChecksNumbers) {
  FlagValues flags;
  flags.Set("k", "7");
  flags.Set("big", "1001");
  flags.Set("neg", "-1");
  flags.Set("radius", "2.5");
  flags.Set("list", "0.5, -1e-3 2");
  EXPECT_EQ(*flags.UintOr("k", 5, 1000), 7u);
  EXPECT_EQ(*flags.UintOr("absent", 5, 1000), 5u);
  EXPECT_FALSE(flags.UintOr("big", 5, 1000).ok());
  EXPECT_FALSE(flags.RequiredUint("neg").ok());
  EXPECT_FALSE(flags.RequiredUint("absent").ok());
  EXPECT_THAT(*flags.RequiredDouble("radius"), DoubleEq(2.5));
  EXPECT_THAT(*flags.RequiredList("list"),
              ElementsAre(DoubleEq(0.5), DoubleEq(-1e-3), DoubleEq(2)));
  EXPECT_FALSE(ParseNumberList("1,nan", "x").ok());
  EXPECT_FALSE(ParseNumberList("1,two", "x").ok());
  EXPECT_FALSE(ParseNumberList(" , ", "x").ok());
}

// ---------------------------------------------------------------------------
// JSON inputs and synthetic traces.

// Issue 48: the write path's two lines started one column off the rest.
TEST(PrintStatsTest, EveryValueStartsInOneColumn) {
  v1::GetStatsResponse stats;
  stats.set_traces(10);
  stats.set_acknowledged_through(7);
  stats.set_applied_through(6);
  stats.set_backlog_traces(3);
  stats.set_backlog_entries(1);
  stats.set_apply_error("disk full");
  std::ostringstream out;
  PrintStats(stats, out);
  std::istringstream lines(out.str());
  std::set<size_t> starts;
  int count = 0;
  for (std::string line; std::getline(lines, line) && !line.empty();) {
    // The value starts after the label and the run of spaces after it.
    const size_t gap = line.find("  ");
    ASSERT_NE(gap, std::string::npos) << line;
    starts.insert(line.find_first_not_of(' ', gap));
    ++count;
  }
  EXPECT_EQ(count, 12) << out.str();
  EXPECT_EQ(starts.size(), 1u) << out.str();
}

TEST(TraceIoTest, ReadsJsonLinesAndNamesTheBadLine) {
  std::istringstream good(
      "{\"robotId\":\"r1\",\"seq\":\"1\",\"code\":[0.5,1]}\n\n"
      "{\"robotId\":\"r1\",\"seq\":2,\"pose\":{\"x\":3}}\n");
  absl::StatusOr<std::vector<v1::MemoryTrace>> traces = ReadTracesJsonl(good);
  ASSERT_TRUE(traces.ok()) << traces.status();
  ASSERT_THAT(*traces, SizeIs(2));
  EXPECT_THAT((*traces)[0].code(), ElementsAre(FloatEq(0.5), FloatEq(1)));
  EXPECT_EQ((*traces)[1].seq(), 2u);
  EXPECT_THAT((*traces)[1].pose().x(), DoubleEq(3));

  std::istringstream bad("{\"robotId\":\"r1\"}\n{\"robotID\":\"typo\"}\n");
  traces = ReadTracesJsonl(bad);
  ASSERT_FALSE(traces.ok());
  EXPECT_THAT(std::string(traces.status().message()), StartsWith("line 2:"));
}

TEST(TraceIoTest, ParsesQueryCodeFromArrayRequestOrTrace) {
  absl::StatusOr<v1::QueryPlaceRequest> query = ParseQueryJson(" [1, 2.5] ");
  ASSERT_TRUE(query.ok()) << query.status();
  EXPECT_THAT(query->code(), ElementsAre(FloatEq(1), FloatEq(2.5)));

  query = ParseQueryJson("{\"code\":[3],\"k\":4,\"radiusM\":2}");
  ASSERT_TRUE(query.ok()) << query.status();
  EXPECT_EQ(query->k(), 4u);
  EXPECT_THAT(query->radius_m(), DoubleEq(2));

  query = ParseQueryJson(
      "{\"robotId\":\"r\",\"seq\":\"3\",\"code\":[0.25],\"pose\":{\"x\":1}}");
  ASSERT_TRUE(query.ok()) << query.status();
  EXPECT_THAT(query->code(), ElementsAre(FloatEq(0.25)));

  EXPECT_FALSE(ParseQueryJson("{\"k\":3}").ok());
  EXPECT_FALSE(ParseQueryJson("not json").ok());
}

double Cosine(const v1::MemoryTrace& a, const v1::MemoryTrace& b) {
  double dot = 0;
  for (int i = 0; i < a.code_size(); ++i) dot += a.code(i) * b.code(i);
  return dot;  // Codes are unit length.
}

TEST(SyntheticTracesTest, SamePlaceOfTwoRobotsHasTheNearestCode) {
  SyntheticTraceOptions options;
  options.robots = 2;
  options.per_robot = 40;
  options.dimension = 64;
  const std::vector<v1::MemoryTrace> traces = GenerateSyntheticTraces(options);
  ASSERT_THAT(traces, SizeIs(80));
  EXPECT_EQ(traces[0].robot_id(), "robot-1");
  EXPECT_EQ(traces[40].robot_id(), "robot-2");
  EXPECT_EQ(traces[39].seq(), 40u);
  EXPECT_NE(traces[0].domain(), traces[40].domain());
  EXPECT_EQ(traces[0].encoder_version(), "v1");
  EXPECT_THAT(Cosine(traces[5], traces[5]), ::testing::DoubleNear(1, 1e-5));
  // For each place of robot 1, robot 2's most similar code is at most two
  // places (10 m) away along the loop, nearly always.
  int near_hits = 0;
  for (int place = 0; place < 40; ++place) {
    int best = -1;
    double best_cosine = -2;
    for (int other = 0; other < 40; ++other) {
      const double cosine = Cosine(traces[place], traces[40 + other]);
      if (cosine > best_cosine) {
        best_cosine = cosine;
        best = other;
      }
    }
    const int offset = std::abs(best - place);
    if (std::min(offset, 40 - offset) <= 2) ++near_hits;
  }
  EXPECT_GE(near_hits, 36);
}

TEST(SyntheticTracesTest, IsDeterministicPerSeed) {
  SyntheticTraceOptions options;
  options.robots = 1;
  options.per_robot = 3;
  options.dimension = 4;
  const auto first = GenerateSyntheticTraces(options);
  const auto again = GenerateSyntheticTraces(options);
  options.seed = 2;
  const auto other = GenerateSyntheticTraces(options);
  EXPECT_EQ(first[2].SerializeAsString(), again[2].SerializeAsString());
  EXPECT_NE(first[2].SerializeAsString(), other[2].SerializeAsString());
}

// ---------------------------------------------------------------------------
// The tool end to end, in process, against a fake server.

class FakeService final : public v1::MemoryService::Service {
 public:
  grpc::Status UploadTraces(grpc::ServerContext*,
                            grpc::ServerReader<v1::UploadTracesRequest>* reader,
                            v1::UploadTracesResponse* response) override {
    v1::UploadTracesRequest request;
    std::lock_guard<std::mutex> lock(mutex_);
    while (reader->Read(&request)) {
      fleet_ = request.fleet_id();
      response->set_accepted(response->accepted() + request.traces_size());
    }
    return grpc::Status::OK;
  }
  grpc::Status QueryPlace(grpc::ServerContext*,
                          const v1::QueryPlaceRequest* request,
                          v1::QueryPlaceResponse* response) override {
    std::lock_guard<std::mutex> lock(mutex_);
    query_ = *request;
    v1::PlaceMatch* match = response->add_matches();
    match->set_distance(0.25f);
    match->mutable_trace()->set_robot_id("robot-9");
    match->mutable_trace()->set_seq(12);
    return grpc::Status::OK;
  }
  grpc::Status GetStats(grpc::ServerContext*, const v1::GetStatsRequest*,
                        v1::GetStatsResponse*) override {
    return grpc::Status(grpc::StatusCode::NOT_FOUND, "no fleet 'nope'");
  }
  grpc::Status WatchMemory(
      grpc::ServerContext* context, const v1::WatchMemoryRequest* request,
      grpc::ServerWriter<v1::MemoryEvent>* writer) override {
    for (uint64_t id = request->after_event() + 1; id <= 5; ++id) {
      v1::MemoryEvent event;
      event.set_id(id);
      event.set_type(v1::MemoryEvent::CLUSTER_FORGOTTEN);
      writer->Write(event);
    }
    while (!context->IsCancelled()) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return grpc::Status::CANCELLED;
  }

  std::string fleet() {
    std::lock_guard<std::mutex> lock(mutex_);
    return fleet_;
  }
  v1::QueryPlaceRequest query() {
    std::lock_guard<std::mutex> lock(mutex_);
    return query_;
  }

 private:
  std::mutex mutex_;
  std::string fleet_;
  v1::QueryPlaceRequest query_;
};

class CliTest : public ::testing::Test {
 protected:
  void SetUp() override {
    grpc::ServerBuilder builder;
    int port = 0;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                             &port);
    builder.RegisterService(&service_);
    server_ = builder.BuildAndStart();
    ASSERT_NE(server_, nullptr);
    server_address_ = "127.0.0.1:" + std::to_string(port);
  }
  void TearDown() override { server_->Shutdown(); }

  // Runs the tool against the fake server (via the environment's default).
  int Run(std::vector<std::string> args, std::string input = "") {
    in_.clear();
    in_.str(std::move(input));
    out_.str("");
    err_.str("");
    CliEnvironment env;
    env.default_server = server_address_;
    env.in = &in_;
    env.out = &out_;
    env.err = &err_;
    return RunCli(args, env);
  }

  FakeService service_;
  std::unique_ptr<grpc::Server> server_;
  std::string server_address_;
  std::istringstream in_;
  std::ostringstream out_;
  std::ostringstream err_;
};

TEST_F(CliTest, HelpAndUsageErrors) {
  EXPECT_EQ(Run({"help"}), 0);
  EXPECT_THAT(out_.str(), HasSubstr("gen-traces"));
  EXPECT_THAT(out_.str(), HasSubstr("--deadline-ms"));

  EXPECT_EQ(Run({"upload", "--help"}), 0);
  EXPECT_THAT(out_.str(), HasSubstr("\nUsage: fleetmem upload --fleet ID"));

  EXPECT_EQ(Run({"help", "gen-traces"}), 0);
  EXPECT_THAT(out_.str(), HasSubstr("SYNTHETIC"));

  EXPECT_EQ(Run({}), 2);
  EXPECT_THAT(err_.str(), HasSubstr("Usage:"));

  EXPECT_EQ(Run({"stats"}), 2);
  EXPECT_THAT(err_.str(), HasSubstr("error: --fleet is required"));

  EXPECT_EQ(Run({"query", "--fleet", "f"}), 2);
  EXPECT_THAT(err_.str(), HasSubstr("one of --code or --code-file"));

  EXPECT_EQ(Run({"query", "--fleet", "f", "--code", "1", "--near", "1,2"}), 2);
  EXPECT_THAT(err_.str(), HasSubstr("--near and --radius go together"));

  EXPECT_EQ(Run({"stats", "--fleet", "f", "--deadline-ms", "0"}), 2);
  EXPECT_EQ(Run({"upload", "--fleet", "f", "--file", "/nonexistent.jsonl"}), 2);
  EXPECT_EQ(Run({"help", "nope"}), 2);
}

TEST_F(CliTest, ServerErrorExitsWithOneAndPrintsTheCode) {
  EXPECT_EQ(Run({"stats", "--fleet", "nope"}), 1);
  EXPECT_EQ(err_.str(), "error: NOT_FOUND: no fleet 'nope'\n");
  EXPECT_THAT(out_.str(), IsEmpty());
}

TEST_F(CliTest, GeneratedTracesUploadFromStdin) {
  ASSERT_EQ(
      Run({"gen-traces", "--robots", "2", "--per-robot", "3", "--dim", "4"}),
      0);
  const std::string jsonl = out_.str();
  EXPECT_THAT(err_.str(), HasSubstr("wrote 6 synthetic traces"));

  ASSERT_EQ(Run({"upload", "--fleet", "f1", "--file", "-"}, jsonl), 0)
      << err_.str();
  EXPECT_EQ(service_.fleet(), "f1");
  EXPECT_THAT(out_.str(), HasSubstr("accepted"));
  EXPECT_THAT(out_.str(), HasSubstr("6"));

  ASSERT_EQ(Run({"--json", "upload", "--fleet", "f1", "--file", "-"}, jsonl),
            0);
  v1::UploadTracesResponse response;
  ASSERT_TRUE(
      google::protobuf::util::JsonStringToMessage(out_.str(), &response).ok())
      << out_.str();
  EXPECT_EQ(response.accepted(), 6u);
}

TEST_F(CliTest, QuerySendsCodeKAndPrior) {
  ASSERT_EQ(Run({"query", "--fleet", "f2", "--code", "0.5,-0.25", "--k", "3",
                 "--near", "1,2,3", "--radius", "15"}),
            0)
      << err_.str();
  const v1::QueryPlaceRequest query = service_.query();
  EXPECT_EQ(query.fleet_id(), "f2");
  EXPECT_THAT(query.code(), ElementsAre(FloatEq(0.5), FloatEq(-0.25)));
  EXPECT_EQ(query.k(), 3u);
  EXPECT_THAT(query.near().z(), DoubleEq(3));
  EXPECT_THAT(query.radius_m(), DoubleEq(15));
  EXPECT_THAT(out_.str(), HasSubstr("robot-9"));
  EXPECT_THAT(out_.str(), HasSubstr("0.2500"));

  ASSERT_EQ(Run({"query", "--fleet", "f2", "--code-file", "-"}, "[1,2]"), 0);
  EXPECT_EQ(service_.query().k(), 5u);  // The default.
}

TEST_F(CliTest, WatchStopsAfterMaxEvents) {
  ASSERT_EQ(Run({"--json", "watch", "--fleet", "f", "--after", "1",
                 "--max-events", "3"}),
            0)
      << err_.str();
  std::vector<uint64_t> ids;
  std::istringstream lines(out_.str());
  for (std::string line; std::getline(lines, line);) {
    v1::MemoryEvent event;
    ASSERT_TRUE(google::protobuf::util::JsonStringToMessage(line, &event).ok())
        << line;
    ids.push_back(event.id());
  }
  EXPECT_THAT(ids, ElementsAre(2, 3, 4));
  EXPECT_THAT(err_.str(), HasSubstr("last event id: 4"));
}

}  // namespace
}  // namespace fleetmem::cli
