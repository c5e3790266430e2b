// REST/JSON for fleetmem.v1.MemoryService. The route table is read from the
// google.api.http options of the RPCs in memory.proto (so routes and RPCs
// cannot drift apart), each request goes through the same MemoryApi as gRPC,
// and messages use protobuf's canonical JSON mapping (JsonStringToMessage /
// MessageToJsonString). Transport-free: HttpServer adapts cpp-httplib to
// Handle, and tests and the fuzzer call Handle directly.
//
// Streaming RPCs: UploadTraces takes one message per POST; WatchMemory
// answers with server-sent events (text/event-stream): per memory event
// "id: ID", "event: TYPE" and "data: JSON"; an error after the stream began
// is an "event: error" whose data is the error body below, and ends it.
//
// Request building, per route: the JSON body (routes with body "*": an
// object of the request message; unknown fields and wrong types are 400
// naming the field), then the path variables ({fleet_id}), then the query
// parameters (GET: each a scalar field of the request, by its JSON or proto
// name). Errors are {"code": <google.rpc code>, "status": "NOT_FOUND",
// "message": <the gRPC message>} with the usual HTTP status.
#ifndef FLEETMEM_SERVICES_HTTP_REST_GATEWAY_H_
#define FLEETMEM_SERVICES_HTTP_REST_GATEWAY_H_

#include <atomic>
#include <cstddef>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/descriptor.h"
#include "services/auth/authenticator.h"
#include "services/transport/memory_api.h"
#include "services/transport/service_state.h"

namespace fleetmem::http {

struct HttpRequest {
  std::string method;                             // "GET", "POST", ...
  std::string path;                               // decoded, without the query
  std::multimap<std::string, std::string> query;  // decoded
  std::string body;
  // The Authorization header, if sent.
  std::optional<std::string> authorization;
  // The common name of a client certificate verified by TLS.
  std::optional<std::string> certificate_common_name;
  // The connection, "ADDRESS:PORT" (throttles costly token checks).
  std::string peer;
  // The Last-Event-ID header (an EventSource resuming a watch), if sent.
  std::optional<std::string> last_event_id;
  // The Host, Origin and Content-Type headers ("" when not sent): the
  // cross-site checks (RestGateway::CheckSite).
  std::string host;
  std::string origin;
  std::string content_type;
};

struct HttpResponse {
  int status = 200;
  std::string content_type = "application/json";
  std::string body;
  std::vector<std::pair<std::string, std::string>> headers;
  // A streamed body instead of `body` (server-sent events): called once, on
  // the connection's thread, with a function that writes one piece (false
  // once the client is gone; an empty piece writes nothing and says
  // whether the client is still there); the body ends when it returns.
  std::function<void(const std::function<bool(std::string_view)>& write)>
      stream;
};

struct RestOptions {
  // Largest request body accepted; a larger one is 413 (the HTTP server
  // refuses it before reading it all).
  size_t max_body_bytes = 4 << 20;
  // Watches over HTTP (server-sent events) each hold a connection and its
  // thread: at most max_watches at once (429 beyond), each ended after
  // max_watch (the client resumes from its Last-Event-ID), with a comment line
  // every watch_heartbeat while the fleet is quiet (how a closed connection is
  // noticed).
  size_t max_watches = 4;
  absl::Duration max_watch = absl::Minutes(5);
  absl::Duration watch_heartbeat = absl::Seconds(15);
  // How often a quiet watch looks whether its client has gone (a closed
  // connection gives back its slot within this; it took up to
  // watch_heartbeat before: the outside sweep's 429s for 13.7 s).
  absl::Duration watch_liveness = absl::Milliseconds(50);
  // Only requests addressed to a loopback name (Host localhost, 127.x.x.x,
  // [::1], any port; or no Host, which browsers always send) are answered: a
  // server without auth on a loopback port, which a web page could otherwise
  // read through DNS rebinding (a name of the page's that resolves to
  // 127.0.0.1).
  bool loopback_hosts_only = false;
  // Origins (scheme://host[:port]) besides the server's own whose pages may
  // make state-changing calls (POST); others are refused.
  std::vector<std::string> allowed_origins;
  // Answers with lists (traces, matches, clusters, events) are written as
  // they are printed, never whole; the messages they are printed from are
  // held until the client has taken them. Those held by every REST call
  // together stay under max_answer_bytes_in_flight: a call that would
  // pass it reserves max_answer_bytes (what one answer holds while it is
  // built: the server sets twice the engine's max_read_bytes, for the
  // engine's copy and the message) before it runs, keeps the answer's
  // real size
  // while it is written, and waits up to answer_wait for room, then gets
  // 503 (retry). A client that stops reading is cut at the HTTP server's
  // write timeout (5 s), which frees its share. (The third outside sweep:
  // 8 largest pages at once took +793 MiB, 32 readers that never read a
  // 3.36 GB peak.)
  uint64_t max_answer_bytes_in_flight = uint64_t{256} << 20;
  uint64_t max_answer_bytes = uint64_t{64} << 20;
  absl::Duration answer_wait = absl::Seconds(10);
};

// One route of the table.
struct Route {
  std::string verb;                   // "GET" or "POST"
  std::string pattern;                // "/v1/fleets/{fleet_id}/stats"
  std::vector<std::string> segments;  // of the pattern, split once
  bool body = false;                  // the request message is the JSON body
  const google::protobuf::MethodDescriptor* method = nullptr;
  // The RPC streams its answers: served as server-sent events.
  bool server_sent_events = false;
  // Its answer has lists (written as printed), and may hold traces (held
  // within RestOptions::max_answer_bytes_in_flight).
  bool answer_has_lists = false;
  bool answer_holds_traces = false;
};

// The routes of every MemoryService RPC with a google.api.http option that
// `api` serves, in proto order. INVALID_ARGUMENT for an option this gateway
// cannot serve (another verb, a path variable that is not a string field).
absl::StatusOr<std::vector<Route>> RoutesFromProto(
    const transport::MemoryApi& api);

// google.rpc code -> HTTP status (grpc-gateway's mapping).
int HttpStatusFor(absl::StatusCode code);

// `answer` as protobuf's JSON mapping with every field present, printed
// element by element so that its size, not a multiple of it, is what the
// printing holds. Moves the top level's repeated messages out of `answer`.
absl::StatusOr<std::string> AnswerJson(google::protobuf::Message* answer);

// The error body for `status`, from the HttpError message (JSON).
HttpResponse ErrorResponse(const absl::Status& status);

// Thread-safe.
class RestGateway {
 public:
  // `api` and `authenticator` must outlive the gateway; a null
  // `authenticator` means auth is off. `on_call` (may be empty) sees every
  // answered API call with transport "http".
  static absl::StatusOr<std::unique_ptr<RestGateway>> Create(
      transport::MemoryApi* api, const auth::Authenticator* authenticator,
      transport::CallObserver on_call, RestOptions options = {});

  // True if `path` is under the API prefix /v1/ (Handle answers it).
  static bool IsApiPath(const std::string& path);

  // The answer to one request under /v1/: CheckSite's refusal, 404 for an
  // unknown path, 405 for a known path with another verb, else the call's
  // answer.
  HttpResponse Handle(const HttpRequest& request) const;

  // The cross-site checks, for the API and /metrics: PERMISSION_DENIED for a
  // Host that is not a loopback name (with loopback_hosts_only) and for a
  // POST from another site's page (an Origin that is neither the server's
  // own nor allowed); INVALID_ARGUMENT for a POST without credentials whose
  // Content-Type a cross-site form could send (text/plain, form encodings):
  // such a POST must say application/json.
  absl::Status CheckSite(const HttpRequest& request) const;

  const std::vector<Route>& routes() const { return routes_; }

  // The caller's principal (anonymous with auth off); UNAUTHENTICATED for
  // missing or wrong credentials.
  absl::StatusOr<auth::Principal> Authenticate(
      const HttpRequest& request) const;

  // Ends the watches being streamed (within a quarter second) and refuses
  // new ones with UNAVAILABLE: for shutdown, before the HTTP server stops.
  void Shutdown() { stopping_.store(true); }

 private:
  RestGateway(transport::MemoryApi* api,
              const auth::Authenticator* authenticator,
              transport::CallObserver on_call, RestOptions options,
              std::vector<Route> routes);
  HttpResponse Serve(const Route& route,
                     const std::map<std::string, std::string>& variables,
                     const HttpRequest& request, absl::StatusCode* code) const;
  // WatchMemory as server-sent events.
  HttpResponse ServeWatch(const auth::Principal& caller,
                          v1::WatchMemoryRequest request,
                          const HttpRequest& http,
                          absl::StatusCode* code) const;

  transport::MemoryApi* const api_;
  const auth::Authenticator* const authenticator_;
  const transport::CallObserver on_call_;
  const RestOptions options_;
  const std::vector<Route> routes_;
  std::atomic<bool> stopping_{false};
  // Watches being streamed (shared with their streams, which may outlive
  // the gateway's call).
  const std::shared_ptr<std::atomic<size_t>> watches_ =
      std::make_shared<std::atomic<size_t>>(0);
  // Bytes of answers held by REST calls (shared with their streams).
  struct AnswerBudget;
  const std::shared_ptr<AnswerBudget> budget_;
};

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_REST_GATEWAY_H_
