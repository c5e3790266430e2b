#include "clients/cpp/fleetmem_client.h"

#include <algorithm>
#include <condition_variable>
#include <cstdlib>
#include <fstream>
#include <mutex>
#include <random>
#include <sstream>
#include <thread>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "grpc/health/v1/health.grpc.pb.h"
#include "grpcpp/grpcpp.h"
#include "grpcpp/security/credentials.h"
#include "services/common/files.h"

namespace fleetmem::client {
namespace {

// Largest response the client accepts: SampleReplay of 10,000 traces of
// dimension 256 is ~11 MB, above gRPC's default of 4 MB.
constexpr int kMaxReceiveMessageBytes = 64 << 20;

// Transient: UNAVAILABLE, DEADLINE_EXCEEDED, and RESOURCE_EXHAUSTED but for
// a standing limit of the server's, whose message names "limit max_"
// (max_fleets, max_code_dimension, max_traces_per_fleet: docs/api.md): a
// retry meets the same limit.
bool IsRetryable(const grpc::Status& status) {
  const grpc::StatusCode code = status.error_code();
  if (code == grpc::StatusCode::RESOURCE_EXHAUSTED) {
    return !absl::StrContains(status.error_message(), "limit max_");
  }
  return code == grpc::StatusCode::UNAVAILABLE ||
         code == grpc::StatusCode::DEADLINE_EXCEEDED;
}

bool Stopped(const std::atomic<bool>* stop) {
  return stop != nullptr && stop->load();
}

// 16 random hex digits: the request id of one SampleReplay (its retries
// reuse it, so the server counts the replay once).
std::string NewRequestId() {
  thread_local std::mt19937_64 rng{std::random_device{}()};
  return absl::StrFormat("%016x", rng());
}

// Deadline and credentials of one attempt.
void SetDeadline(const ClientOptions& options, grpc::ClientContext* context) {
  context->set_deadline(std::chrono::system_clock::now() + options.deadline);
  if (!options.token.empty()) {
    context->AddMetadata("authorization", "Bearer " + options.token);
  }
}

absl::StatusOr<std::string> ReadFile(const std::string& what,
                                     const std::string& path) {
  absl::StatusOr<std::string> text = files::ReadFile(path);
  if (!text.ok()) {
    return absl::Status(text.status().code(),
                        absl::StrCat(what, " file ", path, ": cannot be read"));
  }
  return text;
}

std::shared_ptr<grpc::ChannelCredentials> ChannelCredentialsFor(
    const ClientOptions& options) {
  if (options.tls_root_certs_pem.empty()) {
    return grpc::InsecureChannelCredentials();
  }
  grpc::SslCredentialsOptions ssl;
  ssl.pem_root_certs = options.tls_root_certs_pem;
  ssl.pem_cert_chain = options.tls_cert_chain_pem;
  ssl.pem_private_key = options.tls_private_key_pem;
  return grpc::SslCredentials(ssl);
}

// Wait before attempt `failures + 1`: uniform in [b/2, b] with
// b = min(initial_backoff * 2^(failures-1), max_backoff).
std::chrono::milliseconds BackoffDelay(const ClientOptions& options,
                                       int failures) {
  std::chrono::milliseconds nominal = options.initial_backoff;
  for (int i = 1; i < failures && nominal < options.max_backoff; ++i) {
    nominal *= 2;
  }
  nominal = std::min(nominal, options.max_backoff);
  if (nominal.count() <= 0) return std::chrono::milliseconds(0);
  thread_local std::minstd_rand rng{std::random_device{}()};
  std::uniform_int_distribution<int64_t> jitter(nominal.count() / 2,
                                                nominal.count());
  return std::chrono::milliseconds(jitter(rng));
}

// Waits `delay` before a retry. The synchronous API makes progress on a
// connection only while some thread is inside a call on the channel (and
// otherwise every 5 s, from gRPC's backup poller), and a call that fails fast
// does not stay long enough. So with a channel, the wait waits on the
// channel's state until the end of the delay, which drives the connection;
// the full delay is still waited, so that a server that answers UNAVAILABLE
// is not called again at once. Without a channel (injected stub), or with an
// injected `sleep`, it just sleeps.
void WaitOnChannel(const ClientOptions& options, grpc::Channel* channel,
                   std::chrono::milliseconds delay) {
  if (options.sleep) {
    options.sleep(delay);
    return;
  }
  if (channel == nullptr) {
    std::this_thread::sleep_for(delay);
    return;
  }
  const auto end = std::chrono::system_clock::now() + delay;
  while (std::chrono::system_clock::now() < end) {
    const grpc_connectivity_state state =
        channel->GetState(/*try_to_connect=*/true);
    if (!channel->WaitForStateChange(state, end)) break;  // `end` reached.
  }
}

// Before a retry wait: a channel in TRANSIENT_FAILURE refuses calls until its
// own reconnect backoff ends; resetting it starts a connection attempt now.
void ResetConnectBackoff(grpc::Channel* channel) {
  if (channel != nullptr) {
    grpc::experimental::ChannelResetConnectionBackoff(channel);
  }
}

// The wait before retry number `failures`.
void WaitBeforeRetry(const ClientOptions& options, grpc::Channel* channel,
                     int failures) {
  ResetConnectBackoff(channel);
  WaitOnChannel(options, channel, BackoffDelay(options, failures));
}

// WaitBeforeRetry in slices of at most `poll`, returning early once `stop`.
void WaitBeforeRetryUnlessStopped(const ClientOptions& options,
                                  grpc::Channel* channel, int failures,
                                  const std::atomic<bool>* stop,
                                  std::chrono::milliseconds poll) {
  ResetConnectBackoff(channel);
  std::chrono::milliseconds delay = BackoffDelay(options, failures);
  const auto slice = std::max(poll, std::chrono::milliseconds(1));
  while (delay.count() > 0 && !Stopped(stop)) {
    const auto step = stop == nullptr ? delay : std::min(delay, slice);
    WaitOnChannel(options, channel, step);
    delay -= step;
  }
}

// Runs `call` with a fresh context and deadline per attempt, retrying
// retryable codes with backoff when `retry` is set.
grpc::Status CallWithRetry(
    const ClientOptions& options, grpc::Channel* channel, bool retry,
    const std::function<grpc::Status(grpc::ClientContext*)>& call) {
  const int max_attempts = retry ? std::max(1, options.max_attempts) : 1;
  for (int attempt = 1;; ++attempt) {
    grpc::ClientContext context;
    SetDeadline(options, &context);
    grpc::Status status = call(&context);
    if (status.ok() || !IsRetryable(status) || attempt >= max_attempts) {
      return status;
    }
    WaitBeforeRetry(options, channel, attempt);
  }
}

// While alive, checks `stop` every `poll` and cancels `context` once it is
// set. Must be destroyed before `context`.
class StopWatcher {
 public:
  StopWatcher(const std::atomic<bool>* stop, std::chrono::milliseconds poll,
              grpc::ClientContext* context) {
    if (stop == nullptr) return;
    thread_ = std::thread([this, stop, poll, context] {
      std::unique_lock<std::mutex> lock(mutex_);
      while (!done_) {
        if (stop->load()) {
          context->TryCancel();
          return;
        }
        done_changed_.wait_for(lock, poll);
      }
    });
  }
  StopWatcher(const StopWatcher&) = delete;
  StopWatcher& operator=(const StopWatcher&) = delete;
  ~StopWatcher() {
    if (!thread_.joinable()) return;
    {
      std::lock_guard<std::mutex> lock(mutex_);
      done_ = true;
    }
    done_changed_.notify_all();
    thread_.join();
  }

 private:
  std::mutex mutex_;
  std::condition_variable done_changed_;
  bool done_ = false;
  std::thread thread_;
};

// One upload stream of `traces` in messages of `batch_size` traces.
grpc::Status UploadOnce(v1::MemoryService::StubInterface& stub,
                        grpc::ClientContext* context, std::string_view fleet_id,
                        std::span<const v1::MemoryTrace> traces,
                        size_t batch_size, v1::UploadAck ack,
                        v1::UploadTracesResponse* response) {
  std::unique_ptr<grpc::ClientWriterInterface<v1::UploadTracesRequest>> writer =
      stub.UploadTraces(context, response);
  for (size_t begin = 0; begin < traces.size(); begin += batch_size) {
    const size_t end = std::min(traces.size(), begin + batch_size);
    v1::UploadTracesRequest request;
    request.set_fleet_id(std::string(fleet_id));
    request.set_ack(ack);
    request.mutable_traces()->Reserve(static_cast<int>(end - begin));
    for (size_t i = begin; i < end; ++i) *request.add_traces() = traces[i];
    // A failed write means the stream is broken; Finish() says why.
    if (!writer->Write(request)) break;
  }
  writer->WritesDone();
  return writer->Finish();
}

}  // namespace

absl::Status FromGrpcStatus(const grpc::Status& status) {
  if (status.ok()) return absl::OkStatus();
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()),
                      status.error_message());
}

absl::Status LoadCredentials(const CredentialSources& sources,
                             ClientOptions* options) {
  std::string token_file = sources.token_file;
  if (token_file.empty()) {
    if (const char* file = std::getenv("FLEETMEM_TOKEN_FILE")) {
      token_file = file;
    } else if (const char* token = std::getenv("FLEETMEM_TOKEN")) {
      options->token = std::string(absl::StripAsciiWhitespace(token));
    }
  }
  if (!token_file.empty()) {
    absl::StatusOr<std::string> token = ReadFile("token", token_file);
    if (!token.ok()) return token.status();
    options->token = std::string(absl::StripAsciiWhitespace(*token));
    if (options->token.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat("token file ", token_file, " is empty"));
    }
  }
  if (sources.cert_file.empty() != sources.key_file.empty()) {
    return absl::InvalidArgumentError(
        "a client certificate needs its key, and a key its certificate");
  }
  if (!sources.cert_file.empty() && sources.ca_file.empty()) {
    return absl::InvalidArgumentError(
        "a client certificate needs TLS: give the server's CA too");
  }
  const struct {
    const std::string& path;
    const char* what;
    std::string* out;
  } files[] = {
      {sources.ca_file, "CA certificate", &options->tls_root_certs_pem},
      {sources.cert_file, "client certificate", &options->tls_cert_chain_pem},
      {sources.key_file, "client key", &options->tls_private_key_pem},
  };
  for (const auto& file : files) {
    if (file.path.empty()) continue;
    absl::StatusOr<std::string> pem = ReadFile(file.what, file.path);
    if (!pem.ok()) return pem.status();
    *file.out = std::move(*pem);
  }
  return absl::OkStatus();
}

namespace {
constexpr int kDnsQueryTimeoutMs = 5000;
}  // namespace

std::unique_ptr<Client> Client::Create(ClientOptions options) {
  grpc::ChannelArguments arguments;
  if (!options.tls_server_name.empty()) {
    arguments.SetSslTargetNameOverride(options.tls_server_name);
  }
  arguments.SetMaxReceiveMessageSize(kMaxReceiveMessageBytes);
  // gRPC's own reconnect backoff (1 s doubling to 120 s by default) would
  // make calls fail fast for up to two minutes after a server restart; keep
  // it on the client's retry schedule instead.
  arguments.SetInt(
      GRPC_ARG_INITIAL_RECONNECT_BACKOFF_MS,
      static_cast<int>(std::max<int64_t>(1, options.initial_backoff.count())));
  arguments.SetInt(
      GRPC_ARG_MAX_RECONNECT_BACKOFF_MS,
      static_cast<int>(std::max<int64_t>(1, options.max_backoff.count())));
  if (options.keepalive_time.count() > 0) {
    arguments.SetInt(GRPC_ARG_KEEPALIVE_TIME_MS,
                     static_cast<int>(options.keepalive_time.count()));
    arguments.SetInt(GRPC_ARG_KEEPALIVE_TIMEOUT_MS,
                     static_cast<int>(options.keepalive_timeout.count()));
    arguments.SetInt(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
    // Pings are the point, not data: no cap on pings without data.
    arguments.SetInt(GRPC_ARG_HTTP2_MAX_PINGS_WITHOUT_DATA, 0);
  }
  // A DNS query sent while the robot is off the network never gets an
  // answer; gRPC's c-ares resolver waits 120 s for one by default, and the
  // channel with it. Give up on a query after 5 s.
  arguments.SetInt(GRPC_ARG_DNS_ARES_QUERY_TIMEOUT_MS, kDnsQueryTimeoutMs);
  // Each client its own subchannels: a new client must not inherit a
  // connection state another one got stuck in (agent.h,
  // reconnect_after_failures).
  arguments.SetInt(GRPC_ARG_USE_LOCAL_SUBCHANNEL_POOL, 1);
  std::shared_ptr<grpc::Channel> channel = grpc::CreateCustomChannel(
      options.target, ChannelCredentialsFor(options), arguments);
  auto client = std::make_unique<Client>(std::move(options),
                                         v1::MemoryService::NewStub(channel));
  client->channel_ = std::move(channel);
  return client;
}

Client::Client(ClientOptions options,
               std::unique_ptr<v1::MemoryService::StubInterface> stub)
    : options_(std::move(options)), stub_(std::move(stub)) {}

absl::StatusOr<v1::UploadTracesResponse> Client::Upload(
    std::string_view fleet_id, std::span<const v1::MemoryTrace> traces) {
  v1::UploadTracesResponse response;
  if (traces.empty()) return response;
  const size_t batch_size = std::max<size_t>(1, options_.upload_batch_size);
  grpc::Status status = CallWithRetry(
      options_, channel_.get(), /*retry=*/true,
      [&](grpc::ClientContext* context) {
        response.Clear();
        return UploadOnce(*stub_, context, fleet_id, traces, batch_size,
                          options_.upload_ack, &response);
      });
  if (!status.ok()) return FromGrpcStatus(status);
  return response;
}

absl::StatusOr<v1::ConsolidateResponse> Client::Consolidate(
    std::string_view fleet_id) {
  v1::ConsolidateRequest request;
  request.set_fleet_id(std::string(fleet_id));
  v1::ConsolidateResponse response;
  grpc::Status status =
      CallWithRetry(options_, channel_.get(), /*retry=*/true,
                    [&](grpc::ClientContext* context) {
                      return stub_->Consolidate(context, request, &response);
                    });
  if (!status.ok()) return FromGrpcStatus(status);
  return response;
}

absl::StatusOr<std::vector<v1::MemoryTrace>> Client::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, uint32_t count) {
  v1::SampleReplayRequest request;
  request.set_fleet_id(std::string(fleet_id));
  request.set_robot_id(std::string(robot_id));
  request.set_count(count);
  return SampleReplay(std::move(request));
}

absl::StatusOr<std::vector<v1::MemoryTrace>> Client::SampleReplay(
    v1::SampleReplayRequest request) {
  if (request.request_id().empty()) request.set_request_id(NewRequestId());
  v1::SampleReplayResponse response;
  grpc::Status status =
      CallWithRetry(options_, channel_.get(), /*retry=*/true,
                    [&](grpc::ClientContext* context) {
                      return stub_->SampleReplay(context, request, &response);
                    });
  if (!status.ok()) return FromGrpcStatus(status);
  return std::vector<v1::MemoryTrace>(
      std::make_move_iterator(response.mutable_traces()->begin()),
      std::make_move_iterator(response.mutable_traces()->end()));
}

absl::StatusOr<v1::QueryPlaceResponse> Client::Query(
    const v1::QueryPlaceRequest& request) {
  v1::QueryPlaceResponse response;
  grpc::Status status =
      CallWithRetry(options_, channel_.get(), /*retry=*/true,
                    [&](grpc::ClientContext* context) {
                      return stub_->QueryPlace(context, request, &response);
                    });
  if (!status.ok()) return FromGrpcStatus(status);
  return response;
}

absl::StatusOr<std::vector<v1::PlaceMatch>> Client::QueryPlace(
    const v1::QueryPlaceRequest& request) {
  absl::StatusOr<v1::QueryPlaceResponse> response = Query(request);
  if (!response.ok()) return response.status();
  return std::vector<v1::PlaceMatch>(
      std::make_move_iterator(response->mutable_matches()->begin()),
      std::make_move_iterator(response->mutable_matches()->end()));
}

absl::StatusOr<v1::GetStatsResponse> Client::GetStats(
    std::string_view fleet_id) {
  v1::GetStatsRequest request;
  request.set_fleet_id(std::string(fleet_id));
  v1::GetStatsResponse response;
  grpc::Status status =
      CallWithRetry(options_, channel_.get(), /*retry=*/true,
                    [&](grpc::ClientContext* context) {
                      return stub_->GetStats(context, request, &response);
                    });
  if (!status.ok()) return FromGrpcStatus(status);
  return response;
}

absl::StatusOr<std::string> Client::CheckHealth(std::string_view service) {
  if (channel_ == nullptr) {
    return absl::FailedPreconditionError("CheckHealth needs a channel");
  }
  grpc::health::v1::HealthCheckRequest request;
  request.set_service(std::string(service));
  grpc::health::v1::HealthCheckResponse response;
  auto stub = grpc::health::v1::Health::NewStub(channel_);
  grpc::Status status =
      CallWithRetry(options_, channel_.get(), /*retry=*/false,
                    [&](grpc::ClientContext* context) {
                      return stub->Check(context, request, &response);
                    });
  if (!status.ok()) return FromGrpcStatus(status);
  return grpc::health::v1::HealthCheckResponse::ServingStatus_Name(
      response.status());
}

namespace {

// One unary call with (or without) retries.
template <typename Request, typename Response, typename Method>
absl::StatusOr<Response> Unary(const ClientOptions& options,
                               grpc::Channel* channel, bool retry,
                               const Request& request, Method method) {
  Response response;
  grpc::Status status =
      CallWithRetry(options, channel, retry, [&](grpc::ClientContext* context) {
        return method(context, request, &response);
      });
  if (!status.ok()) return FromGrpcStatus(status);
  return response;
}

}  // namespace

absl::StatusOr<v1::ListFleetsResponse> Client::ListFleets() {
  return Unary<v1::ListFleetsRequest, v1::ListFleetsResponse>(
      options_, channel_.get(), /*retry=*/true, v1::ListFleetsRequest(),
      [this](grpc::ClientContext* context, const v1::ListFleetsRequest& r,
             v1::ListFleetsResponse* out) {
        return stub_->ListFleets(context, r, out);
      });
}

absl::StatusOr<v1::ListClustersResponse> Client::ListClusters(
    std::string_view fleet_id, bool include_places) {
  v1::ListClustersRequest request;
  request.set_fleet_id(std::string(fleet_id));
  request.set_include_places(include_places);
  return Unary<v1::ListClustersRequest, v1::ListClustersResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::ListClustersRequest& r,
             v1::ListClustersResponse* out) {
        return stub_->ListClusters(context, r, out);
      });
}

absl::StatusOr<v1::CreateFleetResponse> Client::CreateFleet(
    const v1::CreateFleetRequest& request) {
  return Unary<v1::CreateFleetRequest, v1::CreateFleetResponse>(
      options_, channel_.get(), /*retry=*/false, request,
      [this](grpc::ClientContext* context, const v1::CreateFleetRequest& r,
             v1::CreateFleetResponse* out) {
        return stub_->CreateFleet(context, r, out);
      });
}

absl::StatusOr<v1::GetFleetResponse> Client::GetFleet(
    std::string_view fleet_id) {
  v1::GetFleetRequest request;
  request.set_fleet_id(std::string(fleet_id));
  return Unary<v1::GetFleetRequest, v1::GetFleetResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::GetFleetRequest& r,
             v1::GetFleetResponse* out) {
        return stub_->GetFleet(context, r, out);
      });
}

absl::StatusOr<v1::UpdateFleetResponse> Client::UpdateFleet(
    const v1::UpdateFleetRequest& request) {
  return Unary<v1::UpdateFleetRequest, v1::UpdateFleetResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::UpdateFleetRequest& r,
             v1::UpdateFleetResponse* out) {
        return stub_->UpdateFleet(context, r, out);
      });
}

absl::StatusOr<v1::DeleteFleetResponse> Client::DeleteFleet(
    std::string_view fleet_id) {
  v1::DeleteFleetRequest request;
  request.set_fleet_id(std::string(fleet_id));
  return Unary<v1::DeleteFleetRequest, v1::DeleteFleetResponse>(
      options_, channel_.get(), /*retry=*/false, request,
      [this](grpc::ClientContext* context, const v1::DeleteFleetRequest& r,
             v1::DeleteFleetResponse* out) {
        return stub_->DeleteFleet(context, r, out);
      });
}

absl::StatusOr<v1::CreateAliasResponse> Client::CreateAlias(
    std::string_view alias, std::string_view fleet_id) {
  v1::CreateAliasRequest request;
  request.set_alias(std::string(alias));
  request.set_fleet_id(std::string(fleet_id));
  return Unary<v1::CreateAliasRequest, v1::CreateAliasResponse>(
      options_, channel_.get(), /*retry=*/false, request,
      [this](grpc::ClientContext* context, const v1::CreateAliasRequest& r,
             v1::CreateAliasResponse* out) {
        return stub_->CreateAlias(context, r, out);
      });
}

absl::StatusOr<v1::SwitchAliasResponse> Client::SwitchAlias(
    std::string_view alias, std::string_view fleet_id) {
  v1::SwitchAliasRequest request;
  request.set_alias(std::string(alias));
  request.set_fleet_id(std::string(fleet_id));
  return Unary<v1::SwitchAliasRequest, v1::SwitchAliasResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::SwitchAliasRequest& r,
             v1::SwitchAliasResponse* out) {
        return stub_->SwitchAlias(context, r, out);
      });
}

absl::StatusOr<v1::DeleteAliasResponse> Client::DeleteAlias(
    std::string_view alias) {
  v1::DeleteAliasRequest request;
  request.set_alias(std::string(alias));
  return Unary<v1::DeleteAliasRequest, v1::DeleteAliasResponse>(
      options_, channel_.get(), /*retry=*/false, request,
      [this](grpc::ClientContext* context, const v1::DeleteAliasRequest& r,
             v1::DeleteAliasResponse* out) {
        return stub_->DeleteAlias(context, r, out);
      });
}

absl::StatusOr<v1::ListAliasesResponse> Client::ListAliases() {
  return Unary<v1::ListAliasesRequest, v1::ListAliasesResponse>(
      options_, channel_.get(), /*retry=*/true, v1::ListAliasesRequest(),
      [this](grpc::ClientContext* context, const v1::ListAliasesRequest& r,
             v1::ListAliasesResponse* out) {
        return stub_->ListAliases(context, r, out);
      });
}

absl::StatusOr<v1::DeleteTracesResponse> Client::DeleteTraces(
    const v1::DeleteTracesRequest& request) {
  return Unary<v1::DeleteTracesRequest, v1::DeleteTracesResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::DeleteTracesRequest& r,
             v1::DeleteTracesResponse* out) {
        return stub_->DeleteTraces(context, r, out);
      });
}

absl::StatusOr<v1::UpdateRewardsResponse> Client::UpdateRewards(
    const v1::UpdateRewardsRequest& request) {
  return Unary<v1::UpdateRewardsRequest, v1::UpdateRewardsResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::UpdateRewardsRequest& r,
             v1::UpdateRewardsResponse* out) {
        return stub_->UpdateRewards(context, r, out);
      });
}

absl::StatusOr<v1::GetTracesResponse> Client::GetTraces(
    const v1::GetTracesRequest& request) {
  return Unary<v1::GetTracesRequest, v1::GetTracesResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::GetTracesRequest& r,
             v1::GetTracesResponse* out) {
        return stub_->GetTraces(context, r, out);
      });
}

absl::StatusOr<v1::ImportTracesResponse> Client::ImportTraces(
    const v1::ImportTracesRequest& request) {
  return Unary<v1::ImportTracesRequest, v1::ImportTracesResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::ImportTracesRequest& r,
             v1::ImportTracesResponse* out) {
        return stub_->ImportTraces(context, r, out);
      });
}

absl::StatusOr<v1::ListTracesResponse> Client::ListTraces(
    std::string_view fleet_id, uint32_t page_size,
    std::string_view page_token) {
  v1::ListTracesRequest request;
  request.set_fleet_id(std::string(fleet_id));
  request.set_page_size(page_size);
  request.set_page_token(std::string(page_token));
  return Unary<v1::ListTracesRequest, v1::ListTracesResponse>(
      options_, channel_.get(), /*retry=*/true, request,
      [this](grpc::ClientContext* context, const v1::ListTracesRequest& r,
             v1::ListTracesResponse* out) {
        return stub_->ListTraces(context, r, out);
      });
}

absl::StatusOr<v1::CreateSnapshotResponse> Client::CreateSnapshot(
    std::string_view name) {
  v1::CreateSnapshotRequest request;
  request.set_name(std::string(name));
  return Unary<v1::CreateSnapshotRequest, v1::CreateSnapshotResponse>(
      options_, channel_.get(), /*retry=*/false, request,
      [this](grpc::ClientContext* context, const v1::CreateSnapshotRequest& r,
             v1::CreateSnapshotResponse* out) {
        return stub_->CreateSnapshot(context, r, out);
      });
}

absl::StatusOr<uint64_t> Client::Watch(
    std::string_view fleet_id, uint64_t after_event,
    const std::function<bool(const v1::MemoryEvent&)>& on_event,
    const std::atomic<bool>* stop, std::chrono::milliseconds poll) {
  uint64_t last_delivered = after_event;
  int failures = 0;  // Attempts in a row that delivered no event.
  while (!Stopped(stop)) {
    v1::WatchMemoryRequest request;
    request.set_fleet_id(std::string(fleet_id));
    request.set_after_event(last_delivered);
    grpc::ClientContext context;
    SetDeadline(options_, &context);
    StopWatcher stop_watcher(stop, poll, &context);
    std::unique_ptr<grpc::ClientReaderInterface<v1::MemoryEvent>> reader =
        stub_->WatchMemory(&context, request);
    bool progressed = false;
    bool caller_done = false;
    v1::MemoryEvent event;
    while (reader->Read(&event)) {
      if (event.id() <= last_delivered) continue;
      last_delivered = event.id();
      progressed = true;
      if (!on_event(event)) {
        caller_done = true;
        context.TryCancel();
        while (reader->Read(&event)) {
        }
        break;
      }
    }
    const grpc::Status status = reader->Finish();
    if (caller_done || Stopped(stop)) break;
    if (status.error_code() == grpc::StatusCode::DEADLINE_EXCEEDED) {
      failures = 0;  // The attempt's deadline: reopen from the cursor.
      continue;
    }
    // We did not cancel, so CANCELLED means the server dropped the stream
    // (e.g. while shutting down): reconnect like for UNAVAILABLE.
    if (!status.ok() && !IsRetryable(status) &&
        status.error_code() != grpc::StatusCode::CANCELLED) {
      return FromGrpcStatus(status);
    }
    failures = progressed ? 1 : failures + 1;
    if (failures >= std::max(1, options_.max_attempts)) {
      if (status.ok()) {
        return absl::UnavailableError("watch stream closed by the server");
      }
      return FromGrpcStatus(status);
    }
    WaitBeforeRetryUnlessStopped(options_, channel_.get(), failures, stop,
                                 poll);
  }
  return last_delivered;
}

}  // namespace fleetmem::client
