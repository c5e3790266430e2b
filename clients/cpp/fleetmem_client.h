// C++ client of fleetmem.v1.MemoryService for robots and tools. Links only
// the generated API and gRPC. Every attempt of a call carries a deadline of
// now + options.deadline (and the token, if any). Every call is safe to
// repeat and is retried with exponential backoff on UNAVAILABLE,
// DEADLINE_EXCEEDED and RESOURCE_EXHAUSTED (but for a standing limit,
// whose message names "limit max_...": a retry meets it again): uploads are
// idempotent by
// (robot_id, seq), a repeated Consolidate only finds less (or nothing)
// pending, and a SampleReplay carries one request id over its attempts, so
// the server counts the replay once. Other codes are returned at once.
//
// Backoff: before attempt n + 1 the client waits a uniformly random time in
// [b/2, b], b = min(initial_backoff * 2^(n-1), max_backoff).
//
// Thread-safe: one Client may be shared by many threads.
#ifndef FLEETMEM_CLIENTS_CPP_FLEETMEM_CLIENT_H_
#define FLEETMEM_CLIENTS_CPP_FLEETMEM_CLIENT_H_

#include <atomic>
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "fleetmem/v1/memory.grpc.pb.h"
#include "fleetmem/v1/memory.pb.h"

namespace fleetmem::client {

struct ClientOptions {
  // Server address, "host:port".
  std::string target = "127.0.0.1:50051";
  // Deadline of each attempt of a call.
  std::chrono::milliseconds deadline{10000};
  // Attempts per call for retryable failures (1 = no retry).
  int max_attempts = 5;
  // Backoff before the second attempt; doubles up to max_backoff.
  std::chrono::milliseconds initial_backoff{100};
  std::chrono::milliseconds max_backoff{5000};
  // HTTP/2 keepalive pings every keepalive_time, also without calls; a
  // connection whose ping is not answered within keepalive_timeout is
  // dropped and redialled. Without them a connection whose path vanished
  // silently (a robot off the network, a NAT that forgot it) looks READY
  // until TCP gives up, some 15 minutes, and every call on it times out.
  // fleetmem-server accepts pings this often; 0 turns keepalive off.
  std::chrono::milliseconds keepalive_time{20000};
  std::chrono::milliseconds keepalive_timeout{10000};
  // Traces per UploadTracesRequest message of an upload stream (0 acts as 1).
  size_t upload_batch_size = 500;
  // When the server answers an upload (docs/api.md): UPLOAD_ACK_APPLIED
  // (the default here: a query or stats call after Upload sees its traces,
  // and the response counts the consolidations) or UPLOAD_ACK_DURABLE (the
  // answer comes at the durable append, before consolidation: the fast
  // path for robots and bulk loads, which fleetmem-robot and fleetmem-load
  // use). The server's own default, for a request that does not say, is
  // durable.
  v1::UploadAck upload_ack = v1::UPLOAD_ACK_APPLIED;
  // Credentials. `token` ("NAME:SECRET", from fleetmem-credential) is sent
  // as "authorization: Bearer TOKEN" with every call; empty sends none.
  std::string token;
  // TLS: PEM of the CA that signed the server's certificate; empty means a
  // plaintext channel.
  std::string tls_root_certs_pem;
  // Mutual TLS: the client's certificate chain and private key (PEM).
  std::string tls_cert_chain_pem;
  std::string tls_private_key_pem;
  // Name to expect in the server's certificate instead of the target's host
  // (e.g. when dialling an IP address).
  std::string tls_server_name;
  // Waits between attempts instead of the client's own wait (see Create);
  // empty by default. Tests inject a recorder so that no test waits on the
  // real clock.
  std::function<void(std::chrono::milliseconds)> sleep;
};

// Where a client's credentials come from. Secrets are read from files or the
// environment, never from a command line (which `ps` shows).
struct CredentialSources {
  // File holding the token "NAME:SECRET" (surrounding whitespace ignored).
  // Empty: the FLEETMEM_TOKEN_FILE environment variable names the file, or
  // FLEETMEM_TOKEN holds the token itself; neither set means no token.
  std::string token_file;
  // PEM files: the CA of the server's certificate (turns TLS on), and the
  // client's certificate and key for mutual TLS (both or neither).
  std::string ca_file;
  std::string cert_file;
  std::string key_file;
};

// Fills options->token and the TLS fields from `sources`. NOT_FOUND naming
// the file that cannot be read; INVALID_ARGUMENT for an empty token file or
// a certificate without its key.
absl::Status LoadCredentials(const CredentialSources& sources,
                             ClientOptions* options);

class Client {
 public:
  // Creates a client over a new channel to options.target (TLS when
  // options.tls_root_certs_pem is set, else plaintext). Does not
  // connect until the first call. Accepts responses up to 64 MiB. A retry
  // wait of such a client resets the channel's connect backoff and waits on
  // the channel (not in sleep_for), so that a restarted server is reconnected
  // during the wait; between calls the channel reconnects on the same
  // initial/max backoff.
  static std::unique_ptr<Client> Create(ClientOptions options);
  // Uses an existing stub (for tests with an in-process channel).
  Client(ClientOptions options,
         std::unique_ptr<v1::MemoryService::StubInterface> stub);

  // Uploads `traces` in one client stream of messages of upload_batch_size
  // traces; a retry repeats the whole stream. Returns the response of the
  // attempt that succeeded, so accepted + duplicates == traces.size(). After
  // a retry, `duplicates` may include traces stored by an earlier failed
  // attempt of the same call (and `consolidations` counts only the last
  // attempt's). An empty `traces` returns zeros without calling the server.
  absl::StatusOr<v1::UploadTracesResponse> Upload(
      std::string_view fleet_id, std::span<const v1::MemoryTrace> traces);
  // Retried; after a retry the counts are those of the last attempt.
  absl::StatusOr<v1::ConsolidateResponse> Consolidate(
      std::string_view fleet_id);
  // Retried with one fresh request id per call: a retry after a lost answer
  // gets the same traces, counted once.
  absl::StatusOr<std::vector<v1::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint32_t count);
  // The same with a whole request (a filter: robots, domains, time,
  // encoder); an empty request_id is given a fresh one.
  absl::StatusOr<std::vector<v1::MemoryTrace>> SampleReplay(
      v1::SampleReplayRequest request);
  absl::StatusOr<std::vector<v1::PlaceMatch>> QueryPlace(
      const v1::QueryPlaceRequest& request);
  // QueryPlace's whole answer: the matches of every code, and the fleet
  // and encoder that answered (through an alias).
  absl::StatusOr<v1::QueryPlaceResponse> Query(
      const v1::QueryPlaceRequest& request);
  absl::StatusOr<v1::GetStatsResponse> GetStats(std::string_view fleet_id);
  // Retried (reads).
  absl::StatusOr<v1::ListFleetsResponse> ListFleets();
  absl::StatusOr<v1::ListClustersResponse> ListClusters(
      std::string_view fleet_id, bool include_places);
  absl::StatusOr<v1::ListTracesResponse> ListTraces(
      std::string_view fleet_id, uint32_t page_size,
      std::string_view page_token);
  // Not retried: a retry after a lost answer would find the fleet made
  // (ALREADY_EXISTS) although this call made it.
  absl::StatusOr<v1::CreateFleetResponse> CreateFleet(
      const v1::CreateFleetRequest& request);
  absl::StatusOr<v1::GetFleetResponse> GetFleet(std::string_view fleet_id);
  // Retried: the same settings set again change nothing.
  absl::StatusOr<v1::UpdateFleetResponse> UpdateFleet(
      const v1::UpdateFleetRequest& request);
  // Admin: removes the fleet and what it holds. Not retried (a retry after
  // a lost answer would say NOT_FOUND, or delete a fleet made since).
  absl::StatusOr<v1::DeleteFleetResponse> DeleteFleet(
      std::string_view fleet_id);
  // Fleet aliases (admin; ListAliases: any caller). Creating is not
  // retried (a retry after a lost answer would say ALREADY_EXISTS); a
  // switch is (the same switch twice ends the same); a delete is not
  // (a retry after a lost answer would say NOT_FOUND).
  absl::StatusOr<v1::CreateAliasResponse> CreateAlias(
      std::string_view alias, std::string_view fleet_id);
  absl::StatusOr<v1::SwitchAliasResponse> SwitchAlias(
      std::string_view alias, std::string_view fleet_id);
  absl::StatusOr<v1::DeleteAliasResponse> DeleteAlias(std::string_view alias);
  absl::StatusOr<v1::ListAliasesResponse> ListAliases();
  // Retried: a repeated delete removes what still matches (nothing, unless
  // traces matching a time range or domain arrived since), and repeated
  // rewards are set again.
  absl::StatusOr<v1::DeleteTracesResponse> DeleteTraces(
      const v1::DeleteTracesRequest& request);
  absl::StatusOr<v1::UpdateRewardsResponse> UpdateRewards(
      const v1::UpdateRewardsRequest& request);
  absl::StatusOr<v1::GetTracesResponse> GetTraces(
      const v1::GetTracesRequest& request);
  // One call of a bulk import (v1.ImportTracesRequest), retried like an
  // upload: rows a failed attempt stored count as duplicates when sent
  // again. The call with `finish` builds the fleet's graph before it
  // answers: give the client a deadline for that (minutes at millions).
  absl::StatusOr<v1::ImportTracesResponse> ImportTraces(
      const v1::ImportTracesRequest& request);
  // grpc.health.v1.Health/Check of `service` ("" = the server as a whole),
  // not retried (a probe wants the answer of now): the serving status's
  // name (SERVING, NOT_SERVING, SERVICE_UNKNOWN, UNKNOWN) or the call's
  // error. Needs a channel (a client made by Create()).
  absl::StatusOr<std::string> CheckHealth(std::string_view service);
  // Not retried: a retry after a lost answer would find the name taken
  // (ALREADY_EXISTS) although the snapshot was made.
  absl::StatusOr<v1::CreateSnapshotResponse> CreateSnapshot(
      std::string_view name);

  // Streams events after `after_event` to `on_event` until it returns false
  // or `stop` becomes true (checked at least every `poll`); reconnects after
  // a broken stream from the last event delivered, so none is missed or
  // repeated (an event whose id is not above the last delivered one is
  // skipped). Returns the id of the last event delivered (`after_event` if
  // none), or the error that ended the watch.
  //
  // How: each attempt is one WatchMemory stream with a deadline of
  // now + options.deadline. When that deadline expires the stream is simply
  // reopened from the cursor (an idle fleet is not an error). UNAVAILABLE,
  // RESOURCE_EXHAUSTED, CANCELLED not caused by this client (a server that
  // shuts down may cancel its streams) and a stream the server ends with OK
  // are retried with backoff; after max_attempts such attempts in a row
  // without an event the last error is returned (UNAVAILABLE for a closed
  // stream). Other codes end the watch. With a `stop` flag, a helper thread per
  // attempt checks it every `poll` and TryCancel()s the stream; backoff waits
  // are cut into slices of `poll` too. `on_event` runs on the calling thread.
  absl::StatusOr<uint64_t> Watch(
      std::string_view fleet_id, uint64_t after_event,
      const std::function<bool(const v1::MemoryEvent&)>& on_event,
      const std::atomic<bool>* stop = nullptr,
      std::chrono::milliseconds poll = std::chrono::milliseconds(500));

  const ClientOptions& options() const { return options_; }

 private:
  ClientOptions options_;
  std::unique_ptr<v1::MemoryService::StubInterface> stub_;
  // The channel of a client made by Create() (null with an injected stub);
  // retry waits drive its reconnection.
  std::shared_ptr<grpc::Channel> channel_;
};

// grpc::Status -> absl::Status (same code and message).
absl::Status FromGrpcStatus(const grpc::Status& status);

}  // namespace fleetmem::client

#endif  // FLEETMEM_CLIENTS_CPP_FLEETMEM_CLIENT_H_
