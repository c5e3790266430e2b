#include "services/http/openapi.h"

#include <set>
#include <utility>

#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "google/protobuf/descriptor.h"
#include "google/protobuf/descriptor.pb.h"
#include "google/protobuf/struct.pb.h"
#include "google/protobuf/util/json_util.h"
#include "services/http/http_error.pb.h"

namespace fleetmem::embedded {
// memory.proto's descriptor set with source info (proto/CMakeLists.txt).
extern const unsigned char kMemoryDescriptorSet[];
extern const unsigned long kMemoryDescriptorSetSize;  // NOLINT(runtime/int)
}  // namespace fleetmem::embedded

namespace fleetmem::http {
namespace {

using google::protobuf::Descriptor;
using google::protobuf::DescriptorPool;
using google::protobuf::EnumDescriptor;
using google::protobuf::FieldDescriptor;
using google::protobuf::Struct;
using google::protobuf::Value;

Value Text(const std::string& text) {
  Value value;
  value.set_string_value(text);
  return value;
}

Value Flag(bool flag) {
  Value value;
  value.set_bool_value(flag);
  return value;
}

// An object value built from (key, value) pairs.
Value Object(std::vector<std::pair<std::string, Value>> members) {
  Value value;
  auto& fields = *value.mutable_struct_value()->mutable_fields();
  for (auto& [key, member] : members) fields[key] = std::move(member);
  return value;
}

// An array value; an empty one stays an array (`[]`), never an unset
// value (which protobuf's JSON printer writes as `{}`).
Value List(std::vector<Value> items) {
  Value value;
  value.mutable_list_value();
  for (Value& item : items) {
    *value.mutable_list_value()->add_values() = std::move(item);
  }
  return value;
}

// The API's descriptors with their comments: the generated code's have no
// source info, so the build embeds memory.proto's descriptor set with it
// (proto/CMakeLists.txt) and this pool is built from it once.
const DescriptorPool* CommentPool() {
  static const DescriptorPool* const pool = [] {
    auto* built = new DescriptorPool();
    google::protobuf::FileDescriptorSet set;
    if (!set.ParseFromArray(
            embedded::kMemoryDescriptorSet,
            static_cast<int>(embedded::kMemoryDescriptorSetSize))) {
      return static_cast<const DescriptorPool*>(built);
    }
    for (const google::protobuf::FileDescriptorProto& file : set.file()) {
      (void)built->BuildFile(file);  // imports first (--include_imports)
    }
    return static_cast<const DescriptorPool*>(built);
  }();
  return pool;
}

// A proto comment as one paragraph (the lines joined, trimmed).
std::string Paragraph(const std::string& comment) {
  std::vector<std::string> words;
  for (absl::string_view word :
       absl::StrSplit(comment, absl::ByAnyChar(" \n"), absl::SkipEmpty())) {
    words.emplace_back(word);
  }
  return absl::StrJoin(words, " ");
}

// The leading comment of the element named `full_name` in memory.proto
// (a message, a field, an enum or a method); empty if none.
template <typename Element>
std::string CommentOf(const Element* element) {
  if (element == nullptr) return "";
  google::protobuf::SourceLocation location;
  if (!element->GetSourceLocation(&location)) return "";
  return Paragraph(location.leading_comments);
}
std::string MessageComment(const Descriptor& type) {
  return CommentOf(CommentPool()->FindMessageTypeByName(type.full_name()));
}
std::string FieldComment(const FieldDescriptor& field) {
  return CommentOf(CommentPool()->FindFieldByName(field.full_name()));
}
std::string MethodComment(const google::protobuf::MethodDescriptor& method) {
  return CommentOf(CommentPool()->FindMethodByName(method.full_name()));
}

// `schema` with `description` added (when there is one).
Value Described(Value schema, const std::string& description) {
  if (!description.empty() && schema.has_struct_value()) {
    (*schema.mutable_struct_value()->mutable_fields())["description"] =
        Text(description);
  }
  return schema;
}

Value Ref(const Descriptor& type) {
  return Object({{"$ref", Text("#/components/schemas/" + type.full_name())}});
}

// The schema of one value of `field` (its element, for repeated fields),
// under protobuf's JSON mapping: 64-bit integers are strings, enums their
// names, bytes base64. Message types are added to `pending`.
Value ScalarSchema(const FieldDescriptor& field,
                   std::set<const Descriptor*>* pending) {
  auto typed = [](const char* type, const char* format) {
    std::vector<std::pair<std::string, Value>> members = {{"type", Text(type)}};
    if (format != nullptr) members.emplace_back("format", Text(format));
    return Object(std::move(members));
  };
  switch (field.type()) {
    case FieldDescriptor::TYPE_DOUBLE:
      return typed("number", "double");
    case FieldDescriptor::TYPE_FLOAT:
      return typed("number", "float");
    case FieldDescriptor::TYPE_INT64:
    case FieldDescriptor::TYPE_SINT64:
    case FieldDescriptor::TYPE_SFIXED64:
      return typed("string", "int64");
    case FieldDescriptor::TYPE_UINT64:
    case FieldDescriptor::TYPE_FIXED64:
      return typed("string", "uint64");
    case FieldDescriptor::TYPE_INT32:
    case FieldDescriptor::TYPE_SINT32:
    case FieldDescriptor::TYPE_SFIXED32:
      return typed("integer", "int32");
    case FieldDescriptor::TYPE_UINT32:
    case FieldDescriptor::TYPE_FIXED32: {
      // 0 .. 2^32-1 does not fit int32: int64, bounded.
      Value schema = typed("integer", "int64");
      auto& fields = *schema.mutable_struct_value()->mutable_fields();
      fields["minimum"].set_number_value(0);
      fields["maximum"].set_number_value(4294967295.0);
      return schema;
    }
    case FieldDescriptor::TYPE_BOOL:
      return typed("boolean", nullptr);
    case FieldDescriptor::TYPE_STRING:
      return typed("string", nullptr);
    case FieldDescriptor::TYPE_BYTES:
      return typed("string", "byte");
    case FieldDescriptor::TYPE_ENUM: {
      const EnumDescriptor& type = *field.enum_type();
      std::vector<Value> names;
      for (int i = 0; i < type.value_count(); ++i) {
        names.push_back(Text(type.value(i)->name()));
      }
      return Object(
          {{"type", Text("string")}, {"enum", List(std::move(names))}});
    }
    case FieldDescriptor::TYPE_MESSAGE:
    case FieldDescriptor::TYPE_GROUP:
      pending->insert(field.message_type());
      return Ref(*field.message_type());
  }
  return typed("string", nullptr);
}

Value FieldSchema(const FieldDescriptor& field,
                  std::set<const Descriptor*>* pending) {
  if (field.is_map()) {  // JSON object: string keys, the map's values
    const FieldDescriptor& value = *field.message_type()->map_value();
    return Object({{"type", Text("object")},
                   {"additionalProperties", ScalarSchema(value, pending)}});
  }
  if (field.is_repeated()) {
    return Object(
        {{"type", Text("array")}, {"items", ScalarSchema(field, pending)}});
  }
  return ScalarSchema(field, pending);
}

Value MessageSchema(const Descriptor& type,
                    std::set<const Descriptor*>* pending) {
  std::vector<std::pair<std::string, Value>> properties;
  for (int i = 0; i < type.field_count(); ++i) {
    const FieldDescriptor& field = *type.field(i);
    // A $ref cannot carry a description beside it (OpenAPI 3.0): those
    // fields are described by their type's schema.
    Value schema = FieldSchema(field, pending);
    if (!schema.struct_value().fields().contains("$ref")) {
      schema = Described(std::move(schema), FieldComment(field));
    }
    properties.emplace_back(field.json_name(), std::move(schema));
  }
  return Described(Object({{"type", Text("object")},
                           {"properties", Object(std::move(properties))}}),
                   MessageComment(type));
}

// An operation's responses: its answer (JSON, or server-sent events) and
// the error every route may give.
Value Responses(const Route& route, std::set<const Descriptor*>* pending) {
  const Descriptor& output = *route.method->output_type();
  pending->insert(&output);
  Value answer =
      route.server_sent_events
          ? Object(
                {{"description",
                  Text(absl::StrCat(
                      "server-sent events: per event `id: ID`, `event: "
                      "TYPE`, `data: ` ",
                      output.full_name(),
                      " as JSON; an `event: error` ends the stream"))},
                 {"content",
                  Object({{"text/event-stream",
                           Object({{"schema",
                                    Object({{"type", Text("string")}})}})}})}})
          : Object(
                {{"description", Text(output.full_name())},
                 {"content", Object({{"application/json",
                                      Object({{"schema", Ref(output)}})}})}});
  pending->insert(HttpError::descriptor());
  return Object(
      {{"200", std::move(answer)},
       {"default",
        Object(
            {{"description", Text("an error: google.rpc code, its name and the "
                                  "server's message")},
             {"content",
              Object({{"application/json",
                       Object({{"schema",
                                Ref(*HttpError::descriptor())}})}})}})}});
}

// "GET /v1/fleets/{fleet_id}/stats" -> GET's operation.
Value Operation(const Route& route, std::set<const Descriptor*>* pending) {
  const Descriptor& input = *route.method->input_type();
  std::vector<Value> parameters;
  std::set<std::string> in_path;
  for (absl::string_view segment :
       absl::StrSplit(route.pattern, '/', absl::SkipEmpty())) {
    if (segment.size() < 3 || segment.front() != '{') continue;
    const std::string name(segment.substr(1, segment.size() - 2));
    in_path.insert(name);
    parameters.push_back(
        Object({{"name", Text(name)},
                {"in", Text("path")},
                {"required", Flag(true)},
                {"schema", Object({{"type", Text("string")}})}}));
  }
  std::vector<std::pair<std::string, Value>> operation = {
      {"operationId", Text(route.method->name())},
      {"summary",
       Text(absl::StrCat(
           route.method->full_name(),
           route.server_sent_events ? " as server-sent events" : ""))}};
  if (std::string about = MethodComment(*route.method); !about.empty()) {
    operation.emplace_back("description", Text(about));
  }
  if (route.body) {
    pending->insert(&input);
    operation.emplace_back(
        "requestBody",
        Object({{"required", Flag(false)},
                {"content", Object({{"application/json",
                                     Object({{"schema", Ref(input)}})}})}}));
  } else {
    // The request's scalar fields, by their JSON names (the proto names
    // are accepted too).
    for (int i = 0; i < input.field_count(); ++i) {
      const FieldDescriptor& field = *input.field(i);
      if (field.is_repeated() || in_path.contains(field.name()) ||
          field.cpp_type() == FieldDescriptor::CPPTYPE_MESSAGE) {
        continue;
      }
      std::vector<std::pair<std::string, Value>> parameter = {
          {"name", Text(field.json_name())},
          {"in", Text("query")},
          {"required", Flag(false)},
          {"schema", ScalarSchema(field, pending)}};
      if (std::string about = FieldComment(field); !about.empty()) {
        parameter.emplace_back("description", Text(about));
      }
      parameters.push_back(Object(std::move(parameter)));
    }
  }
  if (!parameters.empty()) {
    operation.emplace_back("parameters", List(std::move(parameters)));
  }
  operation.emplace_back("responses", Responses(route, pending));
  return Object(std::move(operation));
}

}  // namespace

std::string OpenApiJson(const std::vector<Route>& routes,
                        const std::vector<PlainEndpoint>& endpoints,
                        const std::string& version) {
  std::set<const Descriptor*> pending;
  Struct paths;
  for (const Route& route : routes) {
    Value& path = (*paths.mutable_fields())[route.pattern];
    (*path.mutable_struct_value()
          ->mutable_fields())[absl::AsciiStrToLower(route.verb)] =
        Operation(route, &pending);
  }
  for (const PlainEndpoint& endpoint : endpoints) {
    (*paths.mutable_fields())[endpoint.path] = Object(
        {{"get",
          Object(
              {{"summary", Text(endpoint.summary)},
               {"security", List({})},
               {"responses",
                Object({{"200",
                         Object({{"description", Text(endpoint.summary)},
                                 {"content", Object({{endpoint.content_type,
                                                      Object({})}})}})}})}})}});
  }
  // Every message type reachable from the routes.
  Struct schemas;
  std::set<const Descriptor*> done;
  while (!pending.empty()) {
    const Descriptor* type = *pending.begin();
    pending.erase(pending.begin());
    if (!done.insert(type).second) continue;
    (*schemas.mutable_fields())[type->full_name()] =
        MessageSchema(*type, &pending);
  }
  Value document = Object(
      {{"openapi", Text("3.0.3")},
       {"info",
        Object({{"title", Text("fleetmem")},
                {"version", Text(version)},
                {"description",
                 Text("The REST/JSON face of fleetmem.v1.MemoryService "
                      "(proto/fleetmem/v1/memory.proto; docs/api.md): the "
                      "same calls, rights and errors as gRPC, messages in "
                      "protobuf's JSON mapping.")}})},
       {"paths", Value()},
       {"components",
        Object(
            {{"schemas", Value()},
             {"securitySchemes",
              Object(
                  {{"bearer",
                    Object(
                        {{"type", Text("http")},
                         {"scheme", Text("bearer")},
                         {"description",
                          Text("NAME:SECRET from fleetmem-credential "
                               "(when the server has --auth-file)")}})}})}})},
       // Credentials are needed only when the server has --auth-file.
       {"security", List({Object({{"bearer", List({})}}), Object({})})}});
  auto& top = *document.mutable_struct_value()->mutable_fields();
  *top["paths"].mutable_struct_value() = std::move(paths);
  *(*top["components"].mutable_struct_value()->mutable_fields())["schemas"]
       .mutable_struct_value() = std::move(schemas);
  std::string json;
  google::protobuf::util::JsonPrintOptions print;
  print.add_whitespace = true;
  (void)google::protobuf::util::MessageToJsonString(document.struct_value(),
                                                    &json, print);
  return json;
}

}  // namespace fleetmem::http
