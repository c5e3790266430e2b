#include "services/http/rest_gateway.h"

#include <algorithm>
#include <memory>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "google/api/annotations.pb.h"
#include "google/protobuf/message.h"
#include "google/protobuf/util/json_util.h"
#include "services/http/http_error.pb.h"
#include "services/http/strict_json.h"

namespace fleetmem::http {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::Message;
using google::protobuf::MethodDescriptor;
using google::protobuf::Reflection;

constexpr char kService[] = "fleetmem.v1.MemoryService";
constexpr char kApiPrefix[] = "/v1/";

std::vector<std::string> Segments(const std::string& path) {
  return absl::StrSplit(path, '/', absl::SkipEmpty());
}

bool IsVariable(const std::string& segment) {
  return segment.size() > 2 && segment.front() == '{' && segment.back() == '}';
}

std::string VariableName(const std::string& segment) {
  return segment.substr(1, segment.size() - 2);
}

// Matches `path` against a route's segments; the variables' values on
// success.
std::optional<std::map<std::string, std::string>> Match(
    const std::vector<std::string>& want,
    const std::vector<std::string>& path) {
  if (want.size() != path.size()) return std::nullopt;
  std::map<std::string, std::string> variables;
  for (size_t i = 0; i < want.size(); ++i) {
    if (IsVariable(want[i])) {
      variables[VariableName(want[i])] = path[i];
    } else if (want[i] != path[i]) {
      return std::nullopt;
    }
  }
  return variables;
}

HttpResponse JsonResponse(int status, std::string body) {
  HttpResponse response;
  response.status = status;
  response.body = std::move(body);
  return response;
}

// Sets the scalar field `field` of `message` from the text `value` (a query
// parameter); INVALID_ARGUMENT naming the parameter if it does not parse.
absl::Status SetScalar(const std::string& parameter, const std::string& value,
                       const FieldDescriptor& field, Message* message) {
  const Reflection& r = *message->GetReflection();
  auto bad = [&](absl::string_view expected) {
    return absl::InvalidArgumentError(absl::StrCat(
        "query parameter ", parameter, ": \"", value, "\" is not ", expected));
  };
  switch (field.cpp_type()) {
    case FieldDescriptor::CPPTYPE_STRING:
      r.SetString(message, &field, value);
      return absl::OkStatus();
    case FieldDescriptor::CPPTYPE_UINT32: {
      uint32_t v = 0;
      if (!absl::SimpleAtoi(value, &v)) return bad("an unsigned 32-bit number");
      r.SetUInt32(message, &field, v);
      return absl::OkStatus();
    }
    case FieldDescriptor::CPPTYPE_UINT64: {
      uint64_t v = 0;
      if (!absl::SimpleAtoi(value, &v)) return bad("an unsigned 64-bit number");
      r.SetUInt64(message, &field, v);
      return absl::OkStatus();
    }
    case FieldDescriptor::CPPTYPE_INT32: {
      int32_t v = 0;
      if (!absl::SimpleAtoi(value, &v)) return bad("a 32-bit number");
      r.SetInt32(message, &field, v);
      return absl::OkStatus();
    }
    case FieldDescriptor::CPPTYPE_INT64: {
      int64_t v = 0;
      if (!absl::SimpleAtoi(value, &v)) return bad("a 64-bit number");
      r.SetInt64(message, &field, v);
      return absl::OkStatus();
    }
    case FieldDescriptor::CPPTYPE_DOUBLE: {
      double v = 0;
      if (!absl::SimpleAtod(value, &v)) return bad("a number");
      r.SetDouble(message, &field, v);
      return absl::OkStatus();
    }
    case FieldDescriptor::CPPTYPE_FLOAT: {
      float v = 0;
      if (!absl::SimpleAtof(value, &v)) return bad("a number");
      r.SetFloat(message, &field, v);
      return absl::OkStatus();
    }
    case FieldDescriptor::CPPTYPE_BOOL: {
      bool v = false;
      if (!absl::SimpleAtob(value, &v)) return bad("true or false");
      r.SetBool(message, &field, v);
      return absl::OkStatus();
    }
    default:
      return absl::InvalidArgumentError(absl::StrCat(
          "query parameter ", parameter,
          ": this field cannot be set from the query; use POST with a body"));
  }
}

const FieldDescriptor* FindField(const Descriptor& type,
                                 const std::string& name) {
  const FieldDescriptor* field = type.FindFieldByName(name);
  if (field == nullptr) field = type.FindFieldByCamelcaseName(name);
  return field;
}

google::protobuf::util::JsonPrintOptions PrintOptions() {
  google::protobuf::util::JsonPrintOptions print;
  print.always_print_primitive_fields = true;
  return print;
}

// The top-level repeated message fields of `type` (an answer's lists).
std::vector<const FieldDescriptor*> ListFields(const Descriptor& type) {
  std::vector<const FieldDescriptor*> parts;
  for (int i = 0; i < type.field_count(); ++i) {
    const FieldDescriptor* field = type.field(i);
    if (field->is_repeated() && !field->is_map() &&
        field->cpp_type() == FieldDescriptor::CPPTYPE_MESSAGE) {
      parts.push_back(field);
    }
  }
  return parts;
}

// True if a message of `type` may hold traces (fleetmem.v1.MemoryTrace)
// in a list, at any depth: its answers may be as large as max_read_bytes.
bool HoldsTraces(const Descriptor& type,
                 std::vector<const Descriptor*>* seen = nullptr) {
  std::vector<const Descriptor*> mine;
  if (seen == nullptr) seen = &mine;
  if (std::find(seen->begin(), seen->end(), &type) != seen->end()) {
    return false;
  }
  seen->push_back(&type);
  for (int i = 0; i < type.field_count(); ++i) {
    const FieldDescriptor* field = type.field(i);
    if (field->cpp_type() != FieldDescriptor::CPPTYPE_MESSAGE) continue;
    if (field->is_repeated() &&
        field->message_type()->full_name() == "fleetmem.v1.MemoryTrace") {
      return true;
    }
    if (HoldsTraces(*field->message_type(), seen)) return true;
  }
  return false;
}

// Protobuf's printer with always_print_primitive_fields builds a tree of the
// whole message before it writes a byte (about 200 bytes per number: a
// 4,096-d page of 1,000 traces took 1.2 GB). So the top level's repeated
// messages are printed one element at a time and spliced into the rest,
// whose JSON holds each of them as `"name":[]`: a key cannot appear so inside
// a string, where its quotes are escaped. `write` takes the JSON in pieces
// of about kAnswerPiece bytes, as printed; false from it (the client is
// gone) ends the printing.
constexpr size_t kAnswerPiece = 256 << 10;
absl::Status WriteAnswerJson(
    Message& answer, const std::function<bool(std::string_view)>& write) {
  const google::protobuf::util::JsonPrintOptions print = PrintOptions();
  const std::vector<const FieldDescriptor*> parts =
      ListFields(*answer.GetDescriptor());
  std::unique_ptr<Message> elements(answer.New());
  answer.GetReflection()->SwapFields(&answer, elements.get(), parts);
  std::string envelope;
  if (auto printed =
          google::protobuf::util::MessageToJsonString(answer, &envelope, print);
      !printed.ok()) {
    return absl::InternalError(std::string(printed.message()));
  }
  // Where each list goes, in the envelope's order.
  std::vector<std::pair<size_t, const FieldDescriptor*>> places;
  for (const FieldDescriptor* field : parts) {
    const size_t at =
        envelope.find(absl::StrCat("\"", field->json_name(), "\":[]"));
    if (at == std::string::npos) {
      return absl::InternalError(
          absl::StrCat(field->json_name(), " is not in the answer's JSON"));
    }
    places.emplace_back(at, field);
  }
  std::sort(places.begin(), places.end());
  const Reflection& reflection = *elements->GetReflection();
  std::string json;
  auto flush = [&](bool always) {
    if (!always && json.size() < kAnswerPiece) return true;
    const bool written = json.empty() || write(json);
    json.clear();
    return written;
  };
  size_t copied = 0;
  for (const auto& [at, field] : places) {
    const size_t key_end = at + field->json_name().size() + 4;  // "name":[
    json.append(envelope, copied, key_end - copied);
    const int size = reflection.FieldSize(*elements, field);
    std::string element;
    for (int i = 0; i < size; ++i) {
      if (i > 0) json.push_back(',');
      element.clear();
      if (auto printed = google::protobuf::util::MessageToJsonString(
              reflection.GetRepeatedMessage(*elements, field, i), &element,
              print);
          !printed.ok()) {
        return absl::InternalError(std::string(printed.message()));
      }
      json += element;
      if (!flush(false)) return absl::CancelledError("the client has gone");
    }
    copied = key_end;  // at the list's "]"
  }
  json.append(envelope, copied);
  if (!flush(true)) return absl::CancelledError("the client has gone");
  return absl::OkStatus();
}

}  // namespace

// The whole answer as JSON (small answers, and tests).
absl::StatusOr<std::string> AnswerJson(Message* answer) {
  std::string json;
  absl::Status written = WriteAnswerJson(*answer, [&](std::string_view piece) {
    json.append(piece);
    return true;
  });
  if (!written.ok()) return written;
  return json;
}

int HttpStatusFor(absl::StatusCode code) {
  switch (code) {
    case absl::StatusCode::kOk:
      return 200;
    case absl::StatusCode::kInvalidArgument:
    case absl::StatusCode::kFailedPrecondition:
    case absl::StatusCode::kOutOfRange:
      return 400;
    case absl::StatusCode::kUnauthenticated:
      return 401;
    case absl::StatusCode::kPermissionDenied:
      return 403;
    case absl::StatusCode::kNotFound:
      return 404;
    case absl::StatusCode::kAlreadyExists:
    case absl::StatusCode::kAborted:
      return 409;
    case absl::StatusCode::kResourceExhausted:
      return 429;
    case absl::StatusCode::kCancelled:
      return 499;
    case absl::StatusCode::kUnimplemented:
      return 501;
    case absl::StatusCode::kUnavailable:
      return 503;
    case absl::StatusCode::kDeadlineExceeded:
      return 504;
    default:
      return 500;
  }
}

HttpResponse ErrorResponse(const absl::Status& status) {
  HttpError error;
  error.set_code(static_cast<int32_t>(status.code()));
  error.set_status(absl::StatusCodeToString(status.code()));
  error.set_message(std::string(status.message()));
  std::string body;
  // Cannot fail: the message has only scalar fields.
  (void)google::protobuf::util::MessageToJsonString(error, &body);
  HttpResponse response = JsonResponse(HttpStatusFor(status.code()), body);
  if (status.code() == absl::StatusCode::kUnauthenticated) {
    response.headers.emplace_back("WWW-Authenticate",
                                  "Bearer realm=\"fleetmem\"");
  }
  return response;
}

absl::StatusOr<std::vector<Route>> RoutesFromProto(
    const transport::MemoryApi& api) {
  const google::protobuf::ServiceDescriptor* service =
      google::protobuf::DescriptorPool::generated_pool()->FindServiceByName(
          kService);
  if (service == nullptr) {
    return absl::InternalError(absl::StrCat(kService, " is not linked in"));
  }
  std::vector<Route> routes;
  for (int i = 0; i < service->method_count(); ++i) {
    const MethodDescriptor* method = service->method(i);
    if (!method->options().HasExtension(google::api::http)) continue;
    if (!api.Serves(method->name())) continue;
    const google::api::HttpRule& rule =
        method->options().GetExtension(google::api::http);
    Route route;
    route.method = method;
    route.server_sent_events = method->server_streaming();
    route.answer_has_lists = !ListFields(*method->output_type()).empty();
    route.answer_holds_traces = HoldsTraces(*method->output_type());
    switch (rule.pattern_case()) {
      case google::api::HttpRule::kGet:
        route.verb = "GET";
        route.pattern = rule.get();
        break;
      case google::api::HttpRule::kPost:
        route.verb = "POST";
        route.pattern = rule.post();
        break;
      default:
        return absl::InvalidArgumentError(absl::StrCat(
            method->full_name(), ": only get and post routes are served"));
    }
    if (!rule.body().empty() && rule.body() != "*") {
      return absl::InvalidArgumentError(
          absl::StrCat(method->full_name(), ": body must be \"*\" or empty"));
    }
    route.body = rule.body() == "*";
    if (route.server_sent_events && (route.verb != "GET" || route.body)) {
      return absl::InvalidArgumentError(absl::StrCat(
          method->full_name(), ": a streaming answer is served on GET only"));
    }
    route.segments = Segments(route.pattern);
    for (const std::string& segment : route.segments) {
      if (!IsVariable(segment)) continue;
      const FieldDescriptor* field =
          method->input_type()->FindFieldByName(VariableName(segment));
      if (field == nullptr || field->is_repeated() ||
          field->cpp_type() != FieldDescriptor::CPPTYPE_STRING) {
        return absl::InvalidArgumentError(
            absl::StrCat(method->full_name(), ": path variable ", segment,
                         " is not a string field of the request"));
      }
    }
    routes.push_back(std::move(route));
  }
  return routes;
}

absl::StatusOr<std::unique_ptr<RestGateway>> RestGateway::Create(
    transport::MemoryApi* api, const auth::Authenticator* authenticator,
    transport::CallObserver on_call, RestOptions options) {
  absl::StatusOr<std::vector<Route>> routes = RoutesFromProto(*api);
  if (!routes.ok()) return routes.status();
  return std::unique_ptr<RestGateway>(new RestGateway(
      api, authenticator, std::move(on_call), options, std::move(*routes)));
}

// Bytes of answers held by REST calls: Reserve before an answer is read,
// Shrink to its size once it is, released when the last holder lets go.
struct RestGateway::AnswerBudget
    : public std::enable_shared_from_this<AnswerBudget> {
  explicit AnswerBudget(uint64_t limit) : limit(limit) {}

  // A hold of `bytes` (at most the whole limit), or null if there was no
  // room within `wait`.
  std::shared_ptr<const uint64_t> Reserve(uint64_t bytes, absl::Duration wait) {
    bytes = std::min(bytes, limit);
    absl::MutexLock lock(&mu);
    auto room = [this, bytes]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
      return held + bytes <= limit;
    };
    if (!mu.AwaitWithTimeout(absl::Condition(&room), wait)) return nullptr;
    held += bytes;
    return Hold(bytes);
  }

  // `hold` replaced by one of `bytes` (no more than it held).
  std::shared_ptr<const uint64_t> Shrink(std::shared_ptr<const uint64_t> hold,
                                         uint64_t bytes) {
    bytes = std::min(bytes, *hold);
    {
      absl::MutexLock lock(&mu);
      held += bytes;  // the old hold is released below
    }
    hold.reset();
    return Hold(bytes);
  }

  std::shared_ptr<const uint64_t> Hold(uint64_t bytes) {
    return std::shared_ptr<const uint64_t>(
        new uint64_t(bytes), [budget = shared_from_this()](const uint64_t* b) {
          {
            absl::MutexLock lock(&budget->mu);
            budget->held -= *b;
          }
          delete b;
        });
  }

  const uint64_t limit;
  absl::Mutex mu;
  uint64_t held ABSL_GUARDED_BY(mu) = 0;
};

RestGateway::RestGateway(transport::MemoryApi* api,
                         const auth::Authenticator* authenticator,
                         transport::CallObserver on_call, RestOptions options,
                         std::vector<Route> routes)
    : api_(api),
      authenticator_(authenticator),
      on_call_(std::move(on_call)),
      options_(options),
      routes_(std::move(routes)),
      budget_(std::make_shared<AnswerBudget>(
          std::max(options.max_answer_bytes_in_flight, uint64_t{1}))) {}

bool RestGateway::IsApiPath(const std::string& path) {
  return absl::StartsWith(path, kApiPrefix);
}

absl::StatusOr<auth::Principal> RestGateway::Authenticate(
    const HttpRequest& request) const {
  if (authenticator_ == nullptr) return auth::Principal::Anonymous();
  auth::PresentedCredentials presented;
  if (request.authorization.has_value()) {
    presented.token = auth::TokenFromAuthorization(*request.authorization);
  }
  presented.certificate_common_name = request.certificate_common_name;
  presented.peer = request.peer;
  return authenticator_->Authenticate(presented);
}

namespace {

// `host` without its port ("[::1]:8080" -> "::1", "a:80" -> "a").
std::string HostName(absl::string_view host) {
  if (absl::StartsWith(host, "[")) {
    const size_t end = host.find(']');
    return std::string(host.substr(
        1, end == absl::string_view::npos ? absl::string_view::npos : end - 1));
  }
  return std::string(host.substr(0, host.find(':')));
}

bool IsLoopbackName(absl::string_view host) {
  const std::string name = absl::AsciiStrToLower(HostName(host));
  return name == "localhost" || absl::EndsWith(name, ".localhost") ||
         name == "::1" ||
         (absl::StartsWith(name, "127.") &&
          std::all_of(name.begin(), name.end(), [](char c) {
            return absl::ascii_isdigit(static_cast<unsigned char>(c)) ||
                   c == '.';
          }));
}

}  // namespace

absl::Status RestGateway::CheckSite(const HttpRequest& request) const {
  // A request without Host (HTTP/1.0 tools) is no browser's: browsers
  // always send the name they resolved.
  if (options_.loopback_hosts_only && !request.host.empty() &&
      !IsLoopbackName(request.host)) {
    return absl::PermissionDeniedError(absl::StrCat(
        "Host \"", request.host,
        "\" is not a loopback name: this server has no auth and answers only "
        "requests addressed to localhost or 127.0.0.1 (a page's own name that "
        "resolves here, DNS rebinding, cannot read it)"));
  }
  if (request.method != "POST") return absl::OkStatus();
  if (!request.origin.empty()) {
    const bool own = request.origin == absl::StrCat("http://", request.host) ||
                     request.origin == absl::StrCat("https://", request.host);
    const bool allowed =
        std::find(options_.allowed_origins.begin(),
                  options_.allowed_origins.end(),
                  request.origin) != options_.allowed_origins.end();
    if (!own && !allowed) {
      return absl::PermissionDeniedError(absl::StrCat(
          "a POST from a page of ", request.origin,
          " is refused: only the server's own pages (and allowed origins) may "
          "change its state"));
    }
  }
  const std::string type = absl::AsciiStrToLower(
      request.content_type.substr(0, request.content_type.find(';')));
  const std::string bare(absl::StripAsciiWhitespace(type));
  if (!request.authorization.has_value() &&
      (bare == "text/plain" || bare == "application/x-www-form-urlencoded" ||
       bare == "multipart/form-data")) {
    return absl::InvalidArgumentError(absl::StrCat(
        "a POST without credentials must be Content-Type: application/json, "
        "not ",
        bare, " (which any web page's form may send to this server)"));
  }
  return absl::OkStatus();
}

HttpResponse RestGateway::Handle(const HttpRequest& request) const {
  if (absl::Status site = CheckSite(request); !site.ok()) {
    HttpResponse refused = ErrorResponse(site);
    if (absl::IsInvalidArgument(site)) refused.status = 415;
    return refused;
  }
  const std::vector<std::string> path = Segments(request.path);
  bool path_known = false;
  for (const Route& route : routes_) {
    std::optional<std::map<std::string, std::string>> variables =
        Match(route.segments, path);
    if (!variables.has_value()) continue;
    path_known = true;
    if (route.verb != request.method) continue;
    const absl::Time started = absl::Now();
    absl::StatusCode code = absl::StatusCode::kOk;
    HttpResponse response = Serve(route, *variables, request, &code);
    if (on_call_) {
      on_call_("http", route.method->name(), code,
               absl::ToDoubleSeconds(absl::Now() - started));
    }
    return response;
  }
  if (path_known) {
    HttpResponse response =
        ErrorResponse(absl::InvalidArgumentError(absl::StrCat(
            "method ", request.method, " is not allowed on ", request.path)));
    response.status = 405;
    return response;
  }
  return ErrorResponse(absl::NotFoundError(
      absl::StrCat("no route ", request.method, " ", request.path,
                   " (docs/operations.md lists the REST routes)")));
}

namespace {

// The call's request as the route, the path's variables and the query
// give it: the JSON body (routes with one; strict: no duplicate keys, no
// unknown fields), then the variables, then query parameters (routes
// without a body). INVALID_ARGUMENT naming what is wrong.
absl::StatusOr<std::unique_ptr<Message>> RequestMessage(
    const Route& route, const std::map<std::string, std::string>& variables,
    const HttpRequest& request) {
  const Descriptor& type = *route.method->input_type();
  std::unique_ptr<Message> message(
      google::protobuf::MessageFactory::generated_factory()
          ->GetPrototype(&type)
          ->New());
  if (route.body) {
    const bool blank =
        std::all_of(request.body.begin(), request.body.end(), [](char c) {
          return absl::ascii_isspace(static_cast<unsigned char>(c));
        });
    if (!blank) {
      if (absl::Status strict = CheckStrictJson(request.body, type);
          !strict.ok()) {
        return strict;
      }
      google::protobuf::util::JsonParseOptions options;
      options.ignore_unknown_fields = false;
      const auto parsed = google::protobuf::util::JsonStringToMessage(
          request.body, message.get(), options);
      if (!parsed.ok()) {
        return absl::InvalidArgumentError(
            absl::StrCat("request body: ", std::string(parsed.message())));
      }
    }
  } else if (!request.body.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(request.method, " ", route.pattern,
                     " takes no body; pass fields as query parameters"));
  }
  const Reflection& reflection = *message->GetReflection();
  for (const auto& [name, value] : variables) {
    const FieldDescriptor* field = type.FindFieldByName(name);
    const std::string in_body = reflection.GetString(*message, field);
    if (!in_body.empty() && in_body != value) {
      return absl::InvalidArgumentError(absl::StrCat(
          name, ": the body says \"", in_body, "\", the path \"", value, "\""));
    }
    reflection.SetString(message.get(), field, value);
  }
  for (const auto& [name, value] : request.query) {
    const FieldDescriptor* field = FindField(type, name);
    if (field == nullptr || field->is_repeated() ||
        variables.contains(field->name())) {
      return absl::InvalidArgumentError(absl::StrCat(
          "query parameter ", name, ": not a field of ", type.full_name()));
    }
    if (route.body) {
      return absl::InvalidArgumentError(
          absl::StrCat("query parameter ", name, ": ", route.pattern,
                       " takes its fields in the JSON body"));
    }
    if (absl::Status set = SetScalar(name, value, *field, message.get());
        !set.ok()) {
      return set;
    }
  }
  return message;
}

}  // namespace

HttpResponse RestGateway::Serve(
    const Route& route, const std::map<std::string, std::string>& variables,
    const HttpRequest& request, absl::StatusCode* code) const {
  auto fail = [code](const absl::Status& status) -> HttpResponse {
    *code = status.code();
    return ErrorResponse(status);
  };
  *code = absl::StatusCode::kOk;
  if (request.body.size() > options_.max_body_bytes) {
    HttpResponse response = fail(absl::ResourceExhaustedError(absl::StrCat(
        "request body of ", request.body.size(),
        " bytes is over the server's limit of ", options_.max_body_bytes,
        " bytes (max_http_body_bytes in the server's config "
        "file); nothing was read or done")));
    response.status = 413;
    return response;
  }
  absl::StatusOr<auth::Principal> caller = Authenticate(request);
  if (!caller.ok()) return fail(caller.status());
  absl::StatusOr<std::unique_ptr<Message>> message =
      RequestMessage(route, variables, request);
  if (!message.ok()) return fail(message.status());
  if (route.server_sent_events) {
    if (route.method->name() != "WatchMemory") {
      return fail(absl::UnimplementedError(
          absl::StrCat(route.method->full_name(), " is not served over HTTP")));
    }
    return ServeWatch(*caller,
                      static_cast<const v1::WatchMemoryRequest&>(**message),
                      request, code);
  }
  std::unique_ptr<Message> answer(
      google::protobuf::MessageFactory::generated_factory()
          ->GetPrototype(route.method->output_type())
          ->New());
  if (!route.answer_has_lists) {
    // A small answer: written whole.
    absl::Status status =
        api_->Call(route.method->name(), *caller, **message, answer.get());
    if (!status.ok()) return fail(status);
    absl::StatusOr<std::string> body = AnswerJson(answer.get());
    if (!body.ok()) {
      return fail(absl::InternalError(absl::StrCat(
          "answer cannot be written as JSON: ", body.status().message(),
          " (the call itself succeeded)")));
    }
    return JsonResponse(200, *std::move(body));
  }
  // An answer with lists is written as printed. One that may hold traces
  // has its room reserved before it is read, and keeps its real size while
  // the client takes it.
  std::shared_ptr<const uint64_t> held;
  if (route.answer_holds_traces) {
    held = budget_->Reserve(options_.max_answer_bytes, options_.answer_wait);
    if (held == nullptr) {
      return fail(absl::UnavailableError(absl::StrCat(
          "the server holds max_answer_bytes_in_flight (",
          options_.max_answer_bytes_in_flight,
          " bytes) of REST answers not yet taken by their clients; nothing "
          "was read: retry with backoff")));
    }
  }
  absl::Status status =
      api_->Call(route.method->name(), *caller, **message, answer.get());
  if (!status.ok()) return fail(status);
  if (held != nullptr) {
    held = budget_->Shrink(std::move(held), answer->ByteSizeLong());
  }
  HttpResponse response;
  response.content_type = "application/json";
  response.stream = [answer = std::shared_ptr<Message>(std::move(answer)),
                     held](const std::function<bool(std::string_view)>& write) {
    // The status (200) is sent: a failure here can only end the body
    // early, which the client sees as JSON cut short.
    (void)WriteAnswerJson(*answer, write);
  };
  return response;
}

HttpResponse RestGateway::ServeWatch(const auth::Principal& caller,
                                     v1::WatchMemoryRequest request,
                                     const HttpRequest& http,
                                     absl::StatusCode* code) const {
  auto fail = [code](const absl::Status& status) -> HttpResponse {
    *code = status.code();
    return ErrorResponse(status);
  };
  // An EventSource that reconnects says where it stopped.
  if (http.last_event_id.has_value()) {
    uint64_t resume = 0;
    if (!absl::SimpleAtoi(*http.last_event_id, &resume)) {
      return fail(absl::InvalidArgumentError(absl::StrCat(
          "Last-Event-ID: \"", *http.last_event_id, "\" is not an event id")));
    }
    request.set_after_event(std::max(request.after_event(), resume));
  }
  if (absl::Status allowed = api_->CheckWatch(caller, request).status();
      !allowed.ok()) {
    return fail(allowed);
  }
  if (stopping_.load()) {
    return fail(absl::UnavailableError(
        "the server is shutting down; watch again from your last event id"));
  }
  // The slot is taken here and given back when the stream ends (or when a
  // stream that never ran is destroyed).
  if (watches_->fetch_add(1) >= options_.max_watches) {
    watches_->fetch_sub(1);
    return fail(absl::ResourceExhaustedError(absl::StrCat(
        "limit max_watches (", options_.max_watches,
        ") of watches over HTTP reached; retry later or watch over gRPC")));
  }
  auto slot = std::shared_ptr<void>(
      nullptr, [watches = watches_](void*) { watches->fetch_sub(1); });
  HttpResponse response;
  response.content_type = "text/event-stream";
  response.headers.emplace_back("Cache-Control", "no-cache");
  response.headers.emplace_back("X-Accel-Buffering", "no");
  response.stream = [this, caller, request = std::move(request),
                     slot](const std::function<bool(std::string_view)>& write) {
    const google::protobuf::util::JsonPrintOptions print = PrintOptions();
    // EventSource waits this long (ms) before it reconnects.
    if (!write("retry: 1000\n\n")) return;
    // While the fleet is quiet the watch wakes every watch_liveness to see
    // whether the client has gone (its slot then goes back at once; it
    // went at the next keep-alive write before, up to 15 s later), and
    // writes a keep-alive every watch_heartbeat.
    absl::Time written = absl::Now();
    absl::Status ended = api_->Watch(
        caller, request, absl::Now() + options_.max_watch,
        std::min(options_.watch_liveness, options_.watch_heartbeat), &stopping_,
        [&](const v1::MemoryEvent* event) {
          if (event == nullptr) {
            if (!write("")) return false;  // the client has gone
            if (absl::Now() - written < options_.watch_heartbeat) return true;
            written = absl::Now();
            return write(": keep-alive\n\n");
          }
          written = absl::Now();
          std::string json;
          (void)google::protobuf::util::MessageToJsonString(*event, &json,
                                                            print);
          return write(absl::StrCat("id: ", event->id(), "\nevent: ",
                                    v1::MemoryEvent::Type_Name(event->type()),
                                    "\ndata: ", json, "\n\n"));
        });
    if (!ended.ok()) {
      write(absl::StrCat("event: error\ndata: ", ErrorResponse(ended).body,
                         "\n\n"));
    }
  };
  return response;
}

}  // namespace fleetmem::http
