// The server's one HTTP port (--http-listen), on cpp-httplib: the REST/JSON
// gateway under /v1/, /metrics (Prometheus text format), /healthz and
// /readyz (Kubernetes probes), /openapi.json (openapi.h: the routes and the
// endpoints as served) and the dashboard (/ and its files, embedded in the
// binary). TLS, when the server has a certificate, with the same
// certificate, key and client CA as gRPC. Connections are bounded per client
// and in all, and a request's head and body have deadlines
// (connection_guard.h), so slow clients cannot starve the probes.
//
// Access: /v1/ applies the server's identity and roles (401, 403 as for
// gRPC). /healthz, /readyz, /openapi.json and the dashboard's static files
// need no credentials: the probes carry none, and the page holds no data (it
// asks the person for a reader token when the API answers 401). /metrics
// holds fleet ids and follows auth unless HttpEndpoints::metrics_without_auth.
// RestGateway::CheckSite's cross-site rules apply to /v1/ and /metrics.
#ifndef FLEETMEM_SERVICES_HTTP_HTTP_SERVER_H_
#define FLEETMEM_SERVICES_HTTP_HTTP_SERVER_H_

#include <functional>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/status/statusor.h"
#include "services/http/connection_limits.h"
#include "services/http/openapi.h"
#include "services/http/rest_gateway.h"

namespace httplib {
class Server;
}  // namespace httplib

namespace fleetmem::http {

struct HttpServerOptions {
  // HOST:PORT; port 0 picks a free one (see HttpServer::port()).
  std::string listen;
  // TLS (PEM files) when tls_cert_file is set; client certificates are
  // verified against tls_client_ca_file when set, and required when
  // require_client_certificate. Loaded at start (restart to renew).
  std::string tls_cert_file;
  std::string tls_key_file;
  std::string tls_client_ca_file;
  bool require_client_certificate = false;
  // Largest request body; larger ones get 413 before they are read.
  size_t max_body_bytes = 4 << 20;
  // Connections, per client and in all, and the deadlines of a request
  // (connection_guard.h). Each open connection holds a thread.
  ConnectionLimits connections;
  // The server's version, for /openapi.json.
  std::string version = "unknown";
};

// What the server answers besides the REST routes.
struct HttpEndpoints {
  RestGateway* gateway = nullptr;  // required
  // The /metrics body; 404 if empty.
  std::function<std::string()> metrics;
  // /readyz: true once the store is open and the server serves (and until
  // shutdown begins).
  std::function<bool()> ready;
  // /metrics answers without credentials even with auth on (otherwise it
  // needs a principal's, any role: it holds fleet ids).
  bool metrics_without_auth = false;
  // Lines /readyz adds to its answer (its status stays 200: the server
  // serves), e.g. engine::BacklogWarnings. May be empty.
  std::function<std::vector<std::string>()> warnings;
};

// The endpoints served besides the REST routes and the dashboard's files
// (/healthz, /readyz, /metrics, /openapi.json), as /openapi.json lists them.
const std::vector<PlainEndpoint>& PlainEndpoints();

class HttpServer {
 public:
  // Binds and starts serving on a background thread. INVALID_ARGUMENT for a
  // malformed address or unreadable TLS files, UNAVAILABLE if the address
  // cannot be bound.
  static absl::StatusOr<std::unique_ptr<HttpServer>> Start(
      const HttpServerOptions& options, HttpEndpoints endpoints);
  ~HttpServer();  // Stop()

  // The bound port.
  int port() const { return port_; }
  // Stops accepting, finishes the requests being served, joins the thread.
  // Idempotent.
  void Stop();

 private:
  HttpServer(std::unique_ptr<httplib::Server> server, HttpEndpoints endpoints);

  std::unique_ptr<httplib::Server> server_;
  HttpEndpoints endpoints_;
  int port_ = 0;
  std::thread thread_;
};

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_HTTP_SERVER_H_
