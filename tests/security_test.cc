// Identity, roles and TLS against the real server: principals made with the
// real fleetmem-credential tool, certificates made with openssl.
#include <signal.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <iostream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "grpcpp/create_channel.h"
#include "grpcpp/support/channel_arguments.h"
#include "gtest/gtest.h"
#include "services/common/sanitizers.h"
#include "tests/api_helpers.h"
#include "tests/security_helpers.h"
#include "tests/server_process.h"
#include "tests/synthetic_traces.h"

namespace fleetmem::testing {
namespace {

using ::testing::HasSubstr;

constexpr char kFleet[] = "f1";

std::vector<v1::MemoryTrace> Traces(const std::string& robot, uint64_t first,
                                    size_t count) {
  TraceSpec spec;
  spec.robot_id = robot;
  spec.first_seq = first;
  spec.count = count;
  return MakeTraces(spec);
}

// A server with auth on, and one principal of each kind:
//   robot-7 (robot, fleet f1, token), robot-8 (robot, fleet f1, certificate
//   only), grafana (reader of f1), ops (admin).
class AuthTest : public ::testing::Test {
 protected:
  void SetUp() override {
    credentials_ = dir_.Join("credentials.textproto");
    auto add = [&](const std::string& name, const std::string& role,
                   std::vector<std::string> fleets, std::string* token) {
      absl::StatusOr<std::string> made =
          AddPrincipal(dir_.path(), credentials_, name, role, fleets);
      ASSERT_TRUE(made.ok()) << made.status();
      *token = *made;
    };
    ASSERT_NO_FATAL_FAILURE(add("robot-7", "robot", {kFleet}, &robot7_));
    ASSERT_NO_FATAL_FAILURE(add("grafana", "reader", {kFleet}, &reader_));
    ASSERT_NO_FATAL_FAILURE(add("ops", "admin", {}, &admin_));
    ASSERT_TRUE(AddPrincipal(dir_.path(), credentials_, "robot-8", "robot",
                             {kFleet}, "robot-8")
                    .ok());
  }

  void TearDown() override {
    if (server_ != nullptr && server_->running()) {
      absl::StatusOr<int> code = server_->Stop();
      EXPECT_TRUE(code.ok() && *code == 0) << server_->Output();
    }
    if (HasFailure() && server_ != nullptr) {
      std::cerr << "---- server log ----\n" << server_->Output();
    }
  }

  void Start(std::vector<std::string> extra = {}) {
    ServerOptions options;
    options.data_dir = dir_.Join("data");
    options.log_file = dir_.Join("server.log");
    options.extra_args = {"--auth-file", credentials_};
    options.extra_args.insert(options.extra_args.end(), extra.begin(),
                              extra.end());
    server_ = std::make_unique<ServerProcess>(options);
    absl::Status started = server_->Start();
    ASSERT_TRUE(started.ok()) << started;
  }

  std::unique_ptr<v1::MemoryService::Stub> As(const std::string& token) {
    return MakeSecureStub(server_->address(), {token, "", "", ""});
  }

  TempDir dir_{"fleetmem-auth-"};
  std::string credentials_;
  std::string robot7_, reader_, admin_;
  std::unique_ptr<ServerProcess> server_;
};

TEST_F(AuthTest, NoOrWrongCredentialsAreUnauthenticated) {
  ASSERT_NO_FATAL_FAILURE(Start());
  for (const std::string& token :
       {std::string(), std::string("robot-7:wrong"),
        std::string("nobody:") + robot7_.substr(robot7_.find(':') + 1)}) {
    auto stub = As(token);
    EXPECT_EQ(GetStats(*stub, kFleet).status.error_code(),
              grpc::StatusCode::UNAUTHENTICATED)
        << token;
    EXPECT_EQ(UploadTraces(*stub, kFleet, Traces("robot-7", 1, 3))
                  .status.error_code(),
              grpc::StatusCode::UNAUTHENTICATED);
    EXPECT_EQ(ReadEvents(*stub, kFleet, 0, 1).status.error_code(),
              grpc::StatusCode::UNAUTHENTICATED);
  }
  EXPECT_THAT(GetStats(*As(""), kFleet).status.error_message(),
              HasSubstr("Bearer"));
}

// Issue 32: with auth on, reflection (which takes no credentials) must be
// off unless reflection_with_auth says otherwise.
TEST_F(AuthTest, ReflectionIsOffWithAuth) {
  ASSERT_NO_FATAL_FAILURE(Start());
  std::string response;
  for (const char* method :
       {"/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
        "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo"}) {
    grpc::Status status = ListServicesByReflection(
        MakeChannel(server_->address()), method, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::UNIMPLEMENTED)
        << method << ": " << Describe(status);
  }
  EXPECT_THAT(server_->Output(), HasSubstr("reflection off"));
}

// Issue 32: 64 idle upload streams presenting robot-7's name with a wrong
// secret took every stream slot of "robot-7", and the real robot-7's uploads
// and watches were refused. Slots are now taken after authentication.
// FLEETMEM_IDLE_STREAMS sets the number of streams (100 in make test, over
// max_streams_per_client; docs/security.md reports 1,000); the robot's
// upload time is printed.
TEST_F(AuthTest, WrongSecretsTakeNoStreamSlotsOfTheRobot) {
  ASSERT_NO_FATAL_FAILURE(Start());
  int streams_wanted = 100;
  if (const char* set = std::getenv("FLEETMEM_IDLE_STREAMS")) {
    streams_wanted = std::max(1, std::atoi(set));
  }
  const int kStreams = streams_wanted;
  auto impostor = As("robot-7:WRONG");
  std::vector<std::unique_ptr<grpc::ClientContext>> contexts;
  std::vector<std::unique_ptr<grpc::ClientWriter<v1::UploadTracesRequest>>>
      streams;
  std::vector<v1::UploadTracesResponse> responses(kStreams);
  for (int i = 0; i < kStreams; ++i) {
    contexts.push_back(MakeContext(std::chrono::seconds(30)));
    streams.push_back(
        impostor->UploadTraces(contexts.back().get(), &responses[i]));
  }
  // The robot calls over a connection of its own, as a robot's process
  // does (token checks are rationed per connection; docs/security.md).
  auto robot = MakeSecureStub(server_->address(),
                              {.token = robot7_, .own_connection = true});
  const auto sent = std::chrono::steady_clock::now();
  Reply<v1::UploadTracesResponse> uploaded =
      UploadTraces(*robot, kFleet, Traces("robot-7", 1, 5));
  const double upload_seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - sent)
          .count();
  ASSERT_TRUE(uploaded.ok()) << Describe(uploaded.status);
  EXPECT_EQ(uploaded.response.accepted(), 5u);
  EXPECT_TRUE(ReadEvents(*robot, kFleet, 0, 0, 0).ok());
  std::cout << kStreams << " streams with a wrong secret open; the robot's "
            << "upload took " << upload_seconds << " s\n";
  for (auto& stream : streams) {
    const grpc::Status status = stream->Finish();
    EXPECT_TRUE(status.error_code() == grpc::StatusCode::UNAUTHENTICATED ||
                status.error_code() == grpc::StatusCode::UNAVAILABLE)
        << Describe(status);
  }
}

// What a flood of wrong secrets did: `kAttackers` threads call `wrong(i,
// n)` (a call with a new wrong secret; its status code) at `rate` calls a
// second in all, and, from `delay` after they began, the robot's `call`
// runs every 20 ms for `seconds`.
struct Flood {
  int wrong_calls = 0;
  int wrong_refused = 0;
  int robot_refused = 0;
  // The robot's first call of the flood: on a new connection it pays the
  // one Argon2id check of its token (about 0.1 s, 0.2 s under a sanitizer),
  // so it is reported apart and left out of the percentiles.
  double first_ms = 0;
  std::vector<double> robot_ms;  // the later calls, sorted
  // Nearest rank: of 100 calls, p99 is the 99th fastest, not the slowest.
  double Percentile(double p) const {
    const size_t rank = static_cast<size_t>(std::ceil(robot_ms.size() * p));
    return robot_ms[std::clamp<size_t>(rank, 1, robot_ms.size()) - 1];
  }
};
Flood RunFlood(double rate, double seconds, std::chrono::milliseconds delay,
               const std::function<grpc::StatusCode(int, int)>& wrong,
               const std::function<grpc::StatusCode()>& call) {
  constexpr int kAttackers = 8;
  auto refused = [](grpc::StatusCode code) {
    return code == grpc::StatusCode::UNAUTHENTICATED ||
           code == grpc::StatusCode::UNAVAILABLE;
  };
  std::atomic<bool> stop = false;
  std::atomic<int> wrong_calls = 0, wrong_refused = 0;
  std::vector<std::thread> attackers;
  for (int i = 0; i < kAttackers; ++i) {
    attackers.emplace_back([&, i] {
      const auto period = std::chrono::duration<double>(kAttackers / rate);
      auto next = std::chrono::steady_clock::now();
      for (int n = 0; !stop.load(); ++n) {
        const grpc::StatusCode code = wrong(i, n);
        ++wrong_calls;
        if (refused(code)) ++wrong_refused;
        next += std::chrono::duration_cast<std::chrono::steady_clock::duration>(
            period);
        std::this_thread::sleep_until(next);
      }
    });
  }
  std::this_thread::sleep_for(delay);
  Flood flood;
  const auto start = std::chrono::steady_clock::now();
  const auto end =
      start + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                  std::chrono::duration<double>(seconds));
  // At least kMinRobotCalls under the flood, however slow the machine (an
  // instrumented build beside other tests made 88 in 3 s), within 4 times
  // the flood's time.
  constexpr size_t kMinRobotCalls = 100;
  const auto give_up = start + 4 * (end - start);
  size_t calls = 0;
  while (std::chrono::steady_clock::now() < end ||
         (calls < kMinRobotCalls + 1 &&
          std::chrono::steady_clock::now() < give_up)) {
    const auto sent = std::chrono::steady_clock::now();
    const grpc::StatusCode code = call();
    const double ms = std::chrono::duration<double, std::milli>(
                          std::chrono::steady_clock::now() - sent)
                          .count();
    if (calls++ == 0) {
      flood.first_ms = ms;
    } else {
      flood.robot_ms.push_back(ms);
    }
    if (refused(code)) ++flood.robot_refused;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  stop = true;
  for (std::thread& attacker : attackers) attacker.join();
  std::sort(flood.robot_ms.begin(), flood.robot_ms.end());
  flood.wrong_calls = wrong_calls.load();
  flood.wrong_refused = wrong_refused.load();
  return flood;
}

double FloodSeconds() {
  if (const char* set = std::getenv("FLEETMEM_FLOOD_SECONDS")) {
    return std::max(1.0, std::atof(set));
  }
  return 3;
}

// Issue 32: eight clients sending wrong secrets for a known name raised the
// p50 of legitimate calls from 0.2 ms to 952 ms (every check an Argon2
// hash). Now refused checks are rate-limited and a valid token is checked
// once: the robot's calls during a flood of 50 wrong calls/s. Prints the
// robot's p50 and p99; FLEETMEM_FLOOD_SECONDS sets the flood's length (3 in
// make test; docs/security.md reports 30).
TEST_F(AuthTest, AWrongSecretFloodLeavesTheRobotsCallsFast) {
  ASSERT_NO_FATAL_FAILURE(Start());
  const double flood_seconds = FloodSeconds();
  auto robot = As(robot7_);
  ASSERT_TRUE(GetStats(*robot, kFleet).status.error_code() !=
              grpc::StatusCode::UNAUTHENTICATED);
  const Flood flood = RunFlood(
      50, flood_seconds, std::chrono::milliseconds(0),
      [&](int i, int n) {
        // A new secret every call: no cache can answer it.
        auto impostor = As(
            absl::StrCat(i % 2 == 0 ? "robot-7" : "ops", ":WRONG-", i, "-", n));
        return GetStats(*impostor, kFleet).status.error_code();
      },
      [&] { return GetStats(*robot, kFleet).status.error_code(); });
  ASSERT_FALSE(flood.robot_ms.empty());
  std::cout << flood.wrong_calls << " wrong-secret calls in " << flood_seconds
            << " s (" << flood.wrong_refused << " refused); the robot's "
            << flood.robot_ms.size() << " calls: p50 " << flood.Percentile(0.5)
            << " ms, p99 " << flood.Percentile(0.99) << " ms\n";
  EXPECT_EQ(flood.robot_refused, 0);
  EXPECT_EQ(flood.wrong_refused, flood.wrong_calls);
  // Far above the goal (10 ms) and far below the defect (952 ms): a
  // regression check, not a benchmark.
  EXPECT_LT(flood.Percentile(0.5), 200.0);
}

// A stub on a connection of its own (gRPC shares one connection between
// channels with the same arguments: each attacker, and the robot, would
// otherwise call over one connection).
std::unique_ptr<v1::MemoryService::Stub> StubOnItsOwnConnection(
    const std::string& address) {
  grpc::ChannelArguments args;
  args.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  return v1::MemoryService::NewStub(grpc::CreateCustomChannel(
      address, grpc::InsecureChannelCredentials(), args));
}

// GetStats with `token` sent as metadata on `stub`'s connection.
grpc::StatusCode StatsWithToken(v1::MemoryService::Stub& stub,
                                const std::string& token) {
  grpc::ClientContext context;
  context.AddMetadata("authorization", "Bearer " + token);
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(10));
  v1::GetStatsRequest request;
  request.set_fleet_id(kFleet);
  v1::GetStatsResponse response;
  return stub.GetStats(&context, request, &response).error_code();
}

// The outside sweep: after a restart robot-8's valid token was refused 120
// of 120 times while wrong secrets arrived under its name (checks were
// rationed per name). Eight attackers, each on its own connection, send
// robot-7's name with a new wrong secret at 100 calls a second in all,
// before and after a restart: robot-7's calls (on its connection) are
// never refused, and the p99 of its calls after its first (which pays the
// token's one Argon2id check) stays under 50 ms (80 under a sanitizer).
// FLEETMEM_FLOOD_SECONDS per phase (3).
TEST_F(AuthTest, WrongSecretsUnderTheRobotsNameNeverLockItOut) {
  ASSERT_NO_FATAL_FAILURE(Start());
  for (const bool restarted : {false, true}) {
    SCOPED_TRACE(restarted ? "after a restart" : "before a restart");
    if (restarted) {
      ASSERT_TRUE(server_->Stop().ok());
      ASSERT_NO_FATAL_FAILURE(Start());
    }
    std::vector<std::unique_ptr<v1::MemoryService::Stub>> attackers;
    for (int i = 0; i < 8; ++i) {
      attackers.push_back(StubOnItsOwnConnection(server_->address()));
    }
    auto robot = StubOnItsOwnConnection(server_->address());
    // The flood runs before the robot's first call of the phase (its
    // connections' first checks, one at a time, are done by then). That
    // first call pays the token's check and is reported apart: the bound is
    // on the calls a cached token answers (a check per call, or a call
    // queued behind the attackers' checks, costs one Argon2id, ~100 ms).
    const Flood flood = RunFlood(
        100, FloodSeconds(), std::chrono::milliseconds(1500),
        [&](int i, int n) {
          return StatsWithToken(*attackers[i],
                                absl::StrCat("robot-7:WRONG-", i, "-", n));
        },
        [&] { return StatsWithToken(*robot, robot7_); });
    ASSERT_GE(flood.robot_ms.size(), 100u);
    std::cout << (restarted ? "after" : "before")
              << " a restart: " << flood.wrong_calls
              << " wrong-secret calls under robot-7's "
              << "name (" << flood.wrong_refused << " refused); robot-7's "
              << flood.robot_ms.size() + 1 << " calls: " << flood.robot_refused
              << " refused, the first (its token's check) " << flood.first_ms
              << " ms; the others' p50 " << flood.Percentile(0.5) << " ms, p99 "
              << flood.Percentile(0.99) << " ms, max " << flood.robot_ms.back()
              << " ms\n";
    EXPECT_EQ(flood.robot_refused, 0);
    EXPECT_EQ(flood.wrong_refused, flood.wrong_calls);
    // A call queued behind one attacker's check waits an Argon2id hash
    // (~100 ms; libsodium is not instrumented): 80 ms under a sanitizer,
    // whose server answers a cached call slower (p99 34 ms in CI's run).
    EXPECT_LT(flood.Percentile(0.99),
              common::kSanitizerAllocator ? 80.0 : 50.0);
  }
}

TEST_F(AuthTest, RobotActsOnlyAsItselfInItsFleets) {
  ASSERT_NO_FATAL_FAILURE(Start());
  auto robot = As(robot7_);
  auto admin = As(admin_);
  Reply<v1::UploadTracesResponse> own =
      UploadTraces(*robot, kFleet, Traces("robot-7", 1, 20));
  ASSERT_TRUE(own.ok()) << Describe(own.status);
  EXPECT_EQ(own.response.accepted(), 20u);

  // Another robot's sequence numbers: refused, nothing stored, so the real
  // robot-8's traces are not turned into duplicates.
  Reply<v1::UploadTracesResponse> forged =
      UploadTraces(*robot, kFleet, Traces("robot-8", 1, 5));
  EXPECT_EQ(forged.status.error_code(), grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_THAT(forged.status.error_message(), HasSubstr("robot-8"));
  Reply<v1::GetStatsResponse> stats = GetStats(*admin, kFleet);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(FindRobot(stats.response, "robot-8"), nullptr);
  EXPECT_EQ(stats.response.pending_traces(), 20u);

  // Other fleets, consolidation, replay for another robot: refused.
  EXPECT_EQ(
      UploadTraces(*robot, "f2", Traces("robot-7", 100, 2)).status.error_code(),
      grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(GetStats(*robot, "f2").status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(ReadEvents(*robot, "f2", 0, 1).status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(Consolidate(*robot, kFleet).status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(SampleReplay(*robot, kFleet, "robot-8", 5).status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);

  // What it may do.
  ASSERT_TRUE(Consolidate(*admin, kFleet).ok());
  EXPECT_TRUE(GetStats(*robot, kFleet).ok());
  Reply<v1::SampleReplayResponse> sample =
      SampleReplay(*robot, kFleet, "robot-7", 5);
  ASSERT_TRUE(sample.ok()) << Describe(sample.status);
  EXPECT_EQ(sample.response.traces_size(), 5);
  std::vector<float> code =
      CodeOf(own.ok() ? Traces("robot-7", 1, 1)[0] : v1::MemoryTrace());
  EXPECT_TRUE(QueryCode(*robot, kFleet, code, 1).ok());
}

TEST_F(AuthTest, ReaderCannotWrite) {
  ASSERT_NO_FATAL_FAILURE(Start());
  auto admin = As(admin_);
  ASSERT_TRUE(UploadTraces(*admin, kFleet, Traces("robot-7", 1, 10)).ok());
  auto reader = As(reader_);
  EXPECT_EQ(UploadTraces(*reader, kFleet, Traces("grafana", 1, 1))
                .status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(SampleReplay(*reader, kFleet, "robot-7", 1).status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(Consolidate(*reader, kFleet).status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_TRUE(GetStats(*reader, kFleet).ok());
  std::vector<float> code = CodeOf(Traces("robot-7", 1, 1)[0]);
  EXPECT_TRUE(QueryCode(*reader, kFleet, code, 3).ok());
  // Replay counts were not touched by the refused sample.
  Reply<v1::GetStatsResponse> stats = GetStats(*admin, kFleet);
  ASSERT_TRUE(stats.ok());
  const v1::RobotStats* robot = FindRobot(stats.response, "robot-7");
  ASSERT_NE(robot, nullptr);
  EXPECT_EQ(robot->replayed(), 0u);
}

TEST_F(AuthTest, SighupReloadsTheCredentials) {
  ASSERT_NO_FATAL_FAILURE(Start());
  ASSERT_TRUE(GetStats(*As(robot7_), kFleet).status.error_code() !=
              grpc::StatusCode::UNAUTHENTICATED);
  // A file that does not parse leaves the old credentials in force.
  const std::string good = ReadFileOrEmpty(credentials_);
  std::ofstream(credentials_) << "principal { oops";
  server_->Signal(SIGHUP);
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  EXPECT_NE(GetStats(*As(robot7_), kFleet).status.error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
  // robot-7 revoked: the file is rewritten without it.
  const size_t begin = good.find("principal {\n  name: \"grafana\"");
  ASSERT_NE(begin, std::string::npos);
  std::ofstream(credentials_) << good.substr(begin);
  server_->Signal(SIGHUP);
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(10);
  grpc::StatusCode code = grpc::StatusCode::OK;
  while (std::chrono::steady_clock::now() < end) {
    code = GetStats(*As(robot7_), kFleet).status.error_code();
    if (code == grpc::StatusCode::UNAUTHENTICATED) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
  }
  EXPECT_EQ(code, grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_THAT(server_->Output(), HasSubstr("keeping the previous credentials"));
  EXPECT_NE(GetStats(*As(reader_), kFleet).status.error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
}

TEST(OpenServerTest, RefusesANonLoopbackAddressWithoutAuth) {
  TempDir dir("fleetmem-open-");
  ServerOptions options;
  options.data_dir = dir.Join("data");
  options.log_file = dir.Join("server.log");
  options.listen = "0.0.0.0:0";
  options.start_timeout = std::chrono::milliseconds(10000);
  ServerProcess refused(options);
  absl::Status started = refused.Start();
  EXPECT_FALSE(started.ok());
  EXPECT_THAT(refused.Output(), HasSubstr("--allow-unauthenticated"));

  options.extra_args = {"--allow-unauthenticated"};
  ServerProcess open(options);
  ASSERT_TRUE(open.Start().ok()) << open.Output();
  EXPECT_THAT(open.Output(), HasSubstr("auth is OFF"));
  absl::StatusOr<int> code = open.Stop();
  EXPECT_TRUE(code.ok() && *code == 0);
}

class TlsTest : public AuthTest {
 protected:
  void SetUp() override {
    AuthTest::SetUp();
    ASSERT_TRUE(MakeCertificates(dir_.path(), {"robot-8", "stranger"}).ok());
    ca_ = ReadFileOrEmpty(dir_.Join("ca.pem"));
  }

  void StartTls() {
    Start({"--tls-cert", dir_.Join("server.pem"), "--tls-key",
           dir_.Join("server.key"), "--tls-client-ca", dir_.Join("ca.pem")});
  }

  ChannelSecurity Client(const std::string& name) {
    return {"", ca_, ReadFileOrEmpty(dir_.Join(name + ".pem")),
            ReadFileOrEmpty(dir_.Join(name + ".key"))};
  }

  std::string ca_;
};

TEST_F(TlsTest, TlsClientsConnectAndPlaintextOnesAreRefused) {
  ASSERT_NO_FATAL_FAILURE(StartTls());
  auto tls = MakeSecureStub(server_->address(), {robot7_, ca_, "", ""});
  Reply<v1::UploadTracesResponse> uploaded =
      UploadTraces(*tls, kFleet, Traces("robot-7", 1, 5));
  ASSERT_TRUE(uploaded.ok()) << Describe(uploaded.status);

  auto plaintext = As(robot7_);
  EXPECT_EQ(GetStats(*plaintext, kFleet).status.error_code(),
            grpc::StatusCode::UNAVAILABLE);
  // A client that does not trust the server's CA does not connect either.
  auto untrusting = MakeSecureStub(
      server_->address(),
      {robot7_, ReadFileOrEmpty(dir_.Join("rogue-ca.pem")), "", ""});
  EXPECT_EQ(GetStats(*untrusting, kFleet).status.error_code(),
            grpc::StatusCode::UNAVAILABLE);
}

TEST_F(TlsTest, ClientCertificateNamesTheRobot) {
  ASSERT_NO_FATAL_FAILURE(StartTls());
  // robot-8 has no token: its certificate authenticates it.
  auto robot8 = MakeSecureStub(server_->address(), Client("client-robot-8"));
  Reply<v1::UploadTracesResponse> own =
      UploadTraces(*robot8, kFleet, Traces("robot-8", 1, 5));
  ASSERT_TRUE(own.ok()) << Describe(own.status);
  EXPECT_EQ(UploadTraces(*robot8, kFleet, Traces("robot-7", 1, 5))
                .status.error_code(),
            grpc::StatusCode::PERMISSION_DENIED);
  // A valid certificate whose name is not in the credentials file.
  auto stranger = MakeSecureStub(server_->address(), Client("client-stranger"));
  EXPECT_EQ(GetStats(*stranger, kFleet).status.error_code(),
            grpc::StatusCode::UNAUTHENTICATED);
  // A certificate of another CA with robot-8's name: the handshake fails.
  auto rogue = MakeSecureStub(server_->address(), Client("rogue-client"));
  EXPECT_EQ(UploadTraces(*rogue, kFleet, Traces("robot-8", 10, 1))
                .status.error_code(),
            grpc::StatusCode::UNAVAILABLE);
}

TEST_F(TlsTest, RenewedCertificateIsServedWithoutARestart) {
  const std::string config = dir_.Join("tls.textproto");
  std::ofstream(config) << "security { tls_reload_seconds: 1 }\n";
  // The served files are copies, replaced by rename as a renewal would be.
  ASSERT_TRUE(RunCommand("cd " + dir_.path() +
                         " && cp server.pem live.pem && cp server.key live.key")
                  .ok());
  ASSERT_NO_FATAL_FAILURE(
      Start({"--config", config, "--tls-cert", dir_.Join("live.pem"),
             "--tls-key", dir_.Join("live.key")}));
  const std::string renewed_ca = ReadFileOrEmpty(dir_.Join("rogue-ca.pem"));
  EXPECT_TRUE(
      GetStats(*MakeSecureStub(server_->address(), {admin_, ca_, "", ""}),
               kFleet)
          .status.error_code() != grpc::StatusCode::UNAVAILABLE);
  EXPECT_EQ(GetStats(*MakeSecureStub(server_->address(),
                                     {admin_, renewed_ca, "", ""}),
                     kFleet)
                .status.error_code(),
            grpc::StatusCode::UNAVAILABLE);
  ASSERT_TRUE(RunCommand("cd " + dir_.path() +
                         " && cp server-renewed.key next.key && cp "
                         "server-renewed.pem next.pem && mv next.key live.key "
                         "&& mv next.pem live.pem")
                  .ok());
  grpc::StatusCode code = grpc::StatusCode::UNAVAILABLE;
  const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(15);
  while (code == grpc::StatusCode::UNAVAILABLE &&
         std::chrono::steady_clock::now() < end) {
    std::this_thread::sleep_for(std::chrono::milliseconds(200));
    code = GetStats(*MakeSecureStub(server_->address(),
                                    {admin_, renewed_ca, "", ""}),
                    kFleet)
               .status.error_code();
  }
  EXPECT_NE(code, grpc::StatusCode::UNAVAILABLE)
      << "the renewed certificate was not served";
}

TEST_F(AuthTest, CommandLineToolTakesItsTokenFromAFileOrTheEnvironment) {
  ASSERT_NO_FATAL_FAILURE(Start());
  ASSERT_TRUE(UploadTraces(*As(admin_), kFleet, Traces("robot-7", 1, 3)).ok());
  const std::string tool = std::string(FLEETMEM_BIN_DIR) + "/fleetmem";
  const std::string server = " --server " + server_->address();
  const std::string quiet = " >/dev/null 2>&1";
  EXPECT_FALSE(RunCommand("env -u FLEETMEM_TOKEN -u FLEETMEM_TOKEN_FILE " +
                          tool + server + " stats --fleet f1" + quiet)
                   .ok());
  EXPECT_TRUE(RunCommand(tool + server + " --token-file " +
                         dir_.Join("grafana.token") + " stats --fleet f1" +
                         quiet)
                  .ok());
  EXPECT_TRUE(RunCommand("FLEETMEM_TOKEN_FILE=" + dir_.Join("robot-7.token") +
                         " " + tool + server + " stats --fleet f1" + quiet)
                  .ok());
  EXPECT_TRUE(RunCommand("FLEETMEM_TOKEN=$(cat " + dir_.Join("ops.token") +
                         ") " + tool + server + " consolidate --fleet f1" +
                         quiet)
                  .ok());
  // A reader's token does not consolidate.
  EXPECT_FALSE(RunCommand(tool + server + " --token-file " +
                          dir_.Join("grafana.token") +
                          " consolidate --fleet f1" + quiet)
                   .ok());
}

}  // namespace
}  // namespace fleetmem::testing
