#include "services/http/http_server.h"

#include <openssl/err.h>
#include <openssl/ssl.h>
#include <openssl/x509.h>
#include <sys/socket.h>

#include <chrono>
#include <fstream>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "httplib.h"
#include "services/http/connection_guard.h"
#include "services/http/dashboard_assets.h"
#include "services/http/openapi.h"

namespace fleetmem::http {
namespace {

// /readyz: 200 "ready" (with the warnings' lines) or 503 "not ready".
std::pair<int, std::string> ReadyAnswer(const HttpEndpoints& e) {
  const bool ready = !e.ready || e.ready();
  std::string body = ready ? "ready\n" : "not ready\n";
  if (e.warnings) {
    for (const std::string& line : e.warnings()) {
      absl::StrAppend(&body, line, "\n");
    }
  }
  return {ready ? 200 : 503, std::move(body)};
}

void Answer(HttpResponse from, httplib::Response& to) {
  to.status = from.status;
  for (const auto& [name, value] : from.headers) to.set_header(name, value);
  if (!from.stream) {
    // Moved, not copied (set_content copies): an answer may be tens of MB.
    to.body = std::move(from.body);
    to.set_header("Content-Type", from.content_type);
    return;
  }
  to.set_chunked_content_provider(
      from.content_type,
      [stream = std::move(from.stream)](size_t, httplib::DataSink& sink) {
        stream([&sink](std::string_view piece) {
          if (piece.empty()) {
            return !ConnectionGuard::PeerClosed() && sink.is_writable();
          }
          return sink.is_writable() && sink.write(piece.data(), piece.size());
        });
        sink.done();
        return true;
      });
}

}  // namespace

// The dashboard's files are not an API and are left out.
const std::vector<PlainEndpoint>& PlainEndpoints() {
  static const auto* endpoints = new std::vector<PlainEndpoint>{
      {"/healthz", "text/plain", "liveness: the process answers"},
      {"/readyz", "text/plain",
       "readiness: the store is open and the server serves (503 otherwise)"},
      {"/metrics", "text/plain",
       "Prometheus text format (docs/operations.md lists the metrics)"},
      {"/openapi.json", "application/json", "this description"}};
  return *endpoints;
}

namespace {

// The common name of the client certificate TLS verified, if any.
std::optional<std::string> CertificateCommonName(const httplib::Request& req) {
  if (req.ssl == nullptr) return std::nullopt;
  if (SSL_get_verify_result(req.ssl) != X509_V_OK) return std::nullopt;
  X509* certificate = SSL_get_peer_certificate(req.ssl);
  if (certificate == nullptr) return std::nullopt;
  char name[256] = {0};
  const int length = X509_NAME_get_text_by_NID(
      X509_get_subject_name(certificate), NID_commonName, name, sizeof(name));
  X509_free(certificate);
  if (length <= 0) return std::nullopt;
  return std::string(name, static_cast<size_t>(length));
}

HttpRequest FromHttplib(const httplib::Request& req) {
  HttpRequest request;
  request.method = req.method;
  request.path = req.path;
  // From the target's query only: httplib also puts the fields of a
  // form-encoded body into req.params, and a body is never a query here.
  if (const size_t question = req.target.find('?');
      question != std::string::npos) {
    httplib::Params params;
    httplib::detail::parse_query_text(req.target.substr(question + 1), params);
    for (const auto& [name, value] : params) request.query.emplace(name, value);
  }
  request.body = req.body;
  if (req.has_header("Authorization")) {
    request.authorization = req.get_header_value("Authorization");
  }
  if (req.has_header("Last-Event-ID")) {
    request.last_event_id = req.get_header_value("Last-Event-ID");
  }
  request.certificate_common_name = CertificateCommonName(req);
  request.peer = absl::StrCat(req.remote_addr, ":", req.remote_port);
  request.host = req.get_header_value("Host");
  request.origin = req.get_header_value("Origin");
  request.content_type = req.get_header_value("Content-Type");
  return request;
}

absl::Status CheckReadable(const std::string& path) {
  if (path.empty()) return absl::OkStatus();
  if (!std::ifstream(path)) {
    return absl::InvalidArgumentError(
        absl::StrCat("TLS file ", path, ": cannot be read"));
  }
  return absl::OkStatus();
}

std::string OpenSslError() {
  const unsigned long code = ERR_get_error();
  if (code == 0) return "unknown OpenSSL error";
  char text[256];
  ERR_error_string_n(code, text, sizeof(text));
  return text;
}

absl::StatusOr<std::unique_ptr<httplib::Server>> MakeServer(
    const HttpServerOptions& options) {
  if (options.tls_cert_file.empty()) {
    return std::make_unique<httplib::Server>();
  }
  for (const std::string* path : {&options.tls_cert_file, &options.tls_key_file,
                                  &options.tls_client_ca_file}) {
    if (absl::Status readable = CheckReadable(*path); !readable.ok()) {
      return readable;
    }
  }
  std::string error;
  auto server = std::make_unique<httplib::SSLServer>([&](SSL_CTX& context) {
    if (SSL_CTX_use_certificate_chain_file(
            &context, options.tls_cert_file.c_str()) != 1 ||
        SSL_CTX_use_PrivateKey_file(&context, options.tls_key_file.c_str(),
                                    SSL_FILETYPE_PEM) != 1 ||
        SSL_CTX_check_private_key(&context) != 1) {
      error =
          absl::StrCat("TLS certificate ", options.tls_cert_file, " or key ",
                       options.tls_key_file, ": ", OpenSslError());
      return false;
    }
    SSL_CTX_set_min_proto_version(&context, TLS1_2_VERSION);
    if (!options.tls_client_ca_file.empty()) {
      if (SSL_CTX_load_verify_locations(
              &context, options.tls_client_ca_file.c_str(), nullptr) != 1) {
        error = absl::StrCat("TLS client CA ", options.tls_client_ca_file, ": ",
                             OpenSslError());
        return false;
      }
      // Without "require", a client without a certificate may still connect
      // and present a token; one with a certificate must present a valid one.
      SSL_CTX_set_verify(
          &context,
          SSL_VERIFY_PEER | (options.require_client_certificate
                                 ? SSL_VERIFY_FAIL_IF_NO_PEER_CERT
                                 : 0),
          nullptr);
    }
    return true;
  });
  if (!server->is_valid()) {
    return absl::InvalidArgumentError(
        error.empty() ? "TLS context cannot be set up" : error);
  }
  return server;
}

// HOST and PORT of "HOST:PORT" (":PORT" is every interface; "[::1]:PORT"
// an IPv6 host).
absl::StatusOr<std::pair<std::string, int>> ParseListen(
    const std::string& listen) {
  const size_t colon = listen.rfind(':');
  int port = -1;
  if (colon == std::string::npos ||
      !absl::SimpleAtoi(listen.substr(colon + 1), &port) || port < 0 ||
      port > 65535) {
    return absl::InvalidArgumentError(
        absl::StrCat("http listen address \"", listen, "\" is not HOST:PORT"));
  }
  std::string host = listen.substr(0, colon);
  if (host.empty()) host = "0.0.0.0";
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }
  return std::make_pair(std::move(host), port);
}

// Two Content-Length headers that differ, or one beside Transfer-Encoding,
// frame the body two ways: a proxy in front may read another request into
// it (request smuggling). httplib takes the first; such a request is
// refused and its connection closed.
httplib::Server::HandlerResponse RefuseAmbiguousLength(
    const httplib::Request& req, httplib::Response& res) {
  const size_t lengths = req.get_header_value_count("Content-Length");
  bool ambiguous = lengths > 0 && req.has_header("Transfer-Encoding");
  for (size_t i = 1; i < lengths && !ambiguous; ++i) {
    ambiguous = req.get_header_value("Content-Length", i) !=
                req.get_header_value("Content-Length", 0);
  }
  if (!ambiguous) return httplib::Server::HandlerResponse::Unhandled;
  res.status = 400;
  res.set_header("Connection", "close");
  ConnectionGuard::CloseAfterAnswer();
  res.set_content(
      "{\"code\":3,\"status\":\"INVALID_ARGUMENT\",\"message\":\"the "
      "request's length is ambiguous: Content-Length given twice with "
      "different values, or beside Transfer-Encoding\"}",
      "application/json");
  return httplib::Server::HandlerResponse::Handled;
}

// A write to the API that frames no body at all (no Content-Length, no
// Transfer-Encoding): its body is empty.
bool BodilessWrite(const httplib::Request& req) {
  return (req.method == "POST" || req.method == "PUT" ||
          req.method == "PATCH") &&
         absl::StartsWith(req.path, "/v1/") &&
         !req.has_header("Content-Length") &&
         !req.has_header("Transfer-Encoding");
}

// Bodies over the limit, unknown paths: JSON errors like the API's.
void AnswerErrorAsJson(size_t max_body_bytes, const httplib::Request& req,
                       httplib::Response& res) {
  if (!res.body.empty()) return;
  absl::Status status;
  switch (res.status) {
    case 413:
      status = absl::ResourceExhaustedError(absl::StrCat(
          "request body of ", req.get_header_value("Content-Length"),
          " bytes is over the server's limit of ", max_body_bytes,
          " bytes (max_http_body_bytes in the server's config file); "
          "nothing was read or done"));
      break;
    case 404:
      status = absl::NotFoundError(absl::StrCat("no such page: ", req.path));
      break;
    case 400:
      status = absl::InvalidArgumentError("malformed HTTP request");
      break;
    default:  // the HTTP status stays as httplib set it
      status = absl::UnknownError(absl::StrCat("HTTP status ", res.status));
  }
  HttpResponse error = ErrorResponse(status);
  res.set_content(error.body, error.content_type.c_str());
}

// GET /metrics: the site check, then credentials unless
// metrics_without_auth.
void AnswerMetrics(const HttpEndpoints& e, const httplib::Request& req,
                   httplib::Response& res) {
  if (!e.metrics) {
    res.status = 404;
    return;
  }
  const HttpRequest request = FromHttplib(req);
  absl::Status site = e.gateway->CheckSite(request);
  if (site.ok() && !e.metrics_without_auth) {
    site = e.gateway->Authenticate(request).status();
  }
  if (!site.ok()) {
    HttpResponse refused = ErrorResponse(site);
    res.status = refused.status;
    for (const auto& [name, value] : refused.headers) {
      res.set_header(name, value);
    }
    res.set_content(refused.body, refused.content_type.c_str());
    return;
  }
  res.set_content(e.metrics(), "text/plain; version=0.0.4; charset=utf-8");
}

// The pages beside the API: the OpenAPI document, the probes, /metrics and
// the dashboard's files. No deadline while a handler runs.
void RoutePages(httplib::Server& http, const HttpEndpoints* e,
                const std::string& version) {
  auto get = [&http](const std::string& pattern, httplib::Server::Handler h) {
    http.Get(pattern, [h = std::move(h)](const httplib::Request& req,
                                         httplib::Response& res) {
      ConnectionGuard::Handling();
      h(req, res);
    });
  };
  const std::string openapi =
      OpenApiJson(e->gateway->routes(), PlainEndpoints(), version);
  get("/openapi.json",
      [openapi](const httplib::Request&, httplib::Response& res) {
        res.set_content(openapi, "application/json");
      });
  get("/healthz", [](const httplib::Request&, httplib::Response& res) {
    res.set_content("ok\n", "text/plain");
  });
  get("/readyz", [e](const httplib::Request&, httplib::Response& res) {
    auto [status, body] = ReadyAnswer(*e);
    res.status = status;
    res.set_content(body, "text/plain");
  });
  get("/metrics", [e](const httplib::Request& req, httplib::Response& res) {
    AnswerMetrics(*e, req, res);
  });
  for (const EmbeddedFile& file : DashboardFiles()) {
    auto serve = [&file](const httplib::Request&, httplib::Response& res) {
      res.set_content(reinterpret_cast<const char*>(file.data), file.size,
                      file.content_type);
      res.set_header("Cache-Control", "no-cache");
    };
    get(file.path, serve);
    if (std::string(file.path) == "/index.html") get("/", serve);
  }
  // A watch streams for minutes: no deadline while the gateway answers.
  auto api = [e](const httplib::Request& req, httplib::Response& res) {
    ConnectionGuard::Handling();
    Answer(e->gateway->Handle(FromHttplib(req)), res);
  };
  // A POST without Content-Length or Transfer-Encoding has an empty body
  // (RFC 9112 6.3: `curl -X POST .../consolidate`); httplib would refuse it
  // as malformed (400), so the API answers it before httplib reads.
  http.set_pre_routing_handler(
      [api](const httplib::Request& req, httplib::Response& res) {
        ConnectionGuard::HeadRead();
        const httplib::Server::HandlerResponse refused =
            RefuseAmbiguousLength(req, res);
        if (refused == httplib::Server::HandlerResponse::Handled)
          return refused;
        if (BodilessWrite(req)) {
          api(req, res);
          return httplib::Server::HandlerResponse::Handled;
        }
        return httplib::Server::HandlerResponse::Unhandled;
      });
  http.Get("/v1/.*", api);
  http.Post("/v1/.*", api);
  http.Put("/v1/.*", api);
  http.Delete("/v1/.*", api);
  http.Patch("/v1/.*", api);
}

// Binds HOST:PORT (port 0: any free one) and returns the port, or -1.
// httplib listens with a backlog of 5: a burst of clients (or of slow
// ones) would leave new connections waiting for SYN retries of 1 s and
// more, so the listening socket gets the system's.
int Bind(httplib::Server& http, const std::string& host, int port) {
  int listening = -1;
  http.set_socket_options([&listening](socket_t socket) {
    // httplib's defaults set SO_REUSEPORT too: a second server on a port in
    // use then bound it as well and the kernel split the connections
    // between the two. SO_REUSEADDR alone lets a restart rebind at once
    // and refuses a port another process listens on.
    const int yes = 1;
    ::setsockopt(socket, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
    listening = socket;
  });
  const int bound = port == 0 ? http.bind_to_any_port(host)
                              : (http.bind_to_port(host, port) ? port : -1);
  if (bound > 0 && listening >= 0) ::listen(listening, SOMAXCONN);
  return bound;
}

}  // namespace

absl::StatusOr<std::unique_ptr<HttpServer>> HttpServer::Start(
    const HttpServerOptions& options, HttpEndpoints endpoints) {
  absl::StatusOr<std::pair<std::string, int>> address =
      ParseListen(options.listen);
  if (!address.ok()) return address.status();
  absl::StatusOr<std::unique_ptr<httplib::Server>> made = MakeServer(options);
  if (!made.ok()) return made.status();
  std::unique_ptr<HttpServer> server(
      new HttpServer(std::move(*made), std::move(endpoints)));
  httplib::Server& http = *server->server_;
  HttpEndpoints* e = &server->endpoints_;
  ConnectionLimits limits = options.connections;
  if (options.tls_cert_file.empty()) {
    // Over a connection limit the probes are still answered.
    limits.probe = [e](std::string_view path)
        -> std::optional<std::pair<int, std::string>> {
      if (path == "/healthz") return std::make_pair(200, std::string("ok\n"));
      if (path == "/readyz") return ReadyAnswer(*e);
      return std::nullopt;
    };
  }
  http.new_task_queue = [limits] { return new ConnectionGuard(limits); };
  http.set_payload_max_length(options.max_body_bytes);
  http.set_keep_alive_max_count(100);
  // The guard's deadlines run from these marks (connection_guard.h); the
  // pre-routing handler marks HeadRead (RoutePages).
  http.set_logger([](const httplib::Request&, const httplib::Response&) {
    ConnectionGuard::AnswerSent();
  });
  RoutePages(http, e, options.version);
  http.set_error_handler(
      [limit = options.max_body_bytes](const httplib::Request& req,
                                       httplib::Response& res) {
        AnswerErrorAsJson(limit, req, res);
      });
  server->port_ = Bind(http, address->first, address->second);
  if (server->port_ <= 0) {
    return absl::UnavailableError(
        absl::StrCat("cannot listen for HTTP on ", options.listen));
  }
  server->thread_ = std::thread([&http] { http.listen_after_bind(); });
  // Until it listens: httplib's stop() does nothing before that, and a Stop
  // right after Start would then wait for ever.
  for (int waited_ms = 0; !http.is_running() && waited_ms < 5000; ++waited_ms) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  return server;
}

HttpServer::HttpServer(std::unique_ptr<httplib::Server> server,
                       HttpEndpoints endpoints)
    : server_(std::move(server)), endpoints_(std::move(endpoints)) {}

HttpServer::~HttpServer() { Stop(); }

void HttpServer::Stop() {
  if (!thread_.joinable()) return;
  server_->stop();
  thread_.join();
}

}  // namespace fleetmem::http
