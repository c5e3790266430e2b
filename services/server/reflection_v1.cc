#include "services/server/reflection_v1.h"

#include <algorithm>
#include <utility>

#include "google/protobuf/descriptor.h"
#include "google/protobuf/descriptor.pb.h"

namespace fleetmem::server {
namespace {

using google::protobuf::DescriptorPool;
using google::protobuf::FileDescriptor;
using grpc::reflection::v1::ServerReflectionRequest;
using grpc::reflection::v1::ServerReflectionResponse;

constexpr int kNotFound = static_cast<int>(grpc::StatusCode::NOT_FOUND);
constexpr int kUnimplemented =
    static_cast<int>(grpc::StatusCode::UNIMPLEMENTED);

void Fail(int code, std::string message, ServerReflectionResponse* response) {
  response->mutable_error_response()->set_error_code(code);
  response->mutable_error_response()->set_error_message(std::move(message));
}

// `file` and the files it imports, depth first, each once per stream.
void AddFile(const FileDescriptor* file, std::vector<std::string>* sent,
             ServerReflectionResponse* response) {
  if (std::find(sent->begin(), sent->end(), file->name()) != sent->end()) {
    return;
  }
  sent->push_back(file->name());
  google::protobuf::FileDescriptorProto proto;
  file->CopyTo(&proto);
  response->mutable_file_descriptor_response()->add_file_descriptor_proto(
      proto.SerializeAsString());
  for (int i = 0; i < file->dependency_count(); ++i) {
    AddFile(file->dependency(i), sent, response);
  }
}

}  // namespace

ReflectionV1::ReflectionV1(std::vector<std::string> services)
    : services_(std::move(services)) {}

ServerReflectionResponse ReflectionV1::Answer(
    const ServerReflectionRequest& request,
    std::vector<std::string>* sent) const {
  const DescriptorPool* pool = DescriptorPool::generated_pool();
  ServerReflectionResponse response;
  response.set_valid_host(request.host());
  *response.mutable_original_request() = request;
  // A file asked for again is sent again (the client asked for it), but
  // its imports only once.
  auto file = [&](const FileDescriptor* found, const std::string& what) {
    if (found == nullptr) {
      Fail(kNotFound, what + " not found", &response);
      return;
    }
    sent->erase(std::remove(sent->begin(), sent->end(), found->name()),
                sent->end());
    AddFile(found, sent, &response);
  };
  switch (request.message_request_case()) {
    case ServerReflectionRequest::kFileByFilename:
      file(pool->FindFileByName(request.file_by_filename()),
           "file " + request.file_by_filename());
      break;
    case ServerReflectionRequest::kFileContainingSymbol:
      file(pool->FindFileContainingSymbol(request.file_containing_symbol()),
           "symbol " + request.file_containing_symbol());
      break;
    case ServerReflectionRequest::kFileContainingExtension: {
      const auto& asked = request.file_containing_extension();
      const google::protobuf::Descriptor* type =
          pool->FindMessageTypeByName(asked.containing_type());
      const google::protobuf::FieldDescriptor* extension =
          type == nullptr
              ? nullptr
              : pool->FindExtensionByNumber(type, asked.extension_number());
      file(extension == nullptr ? nullptr : extension->file(),
           "extension " + std::to_string(asked.extension_number()) + " of " +
               asked.containing_type());
      break;
    }
    case ServerReflectionRequest::kAllExtensionNumbersOfType: {
      const google::protobuf::Descriptor* type =
          pool->FindMessageTypeByName(request.all_extension_numbers_of_type());
      if (type == nullptr) {
        Fail(kNotFound,
             "type " + request.all_extension_numbers_of_type() + " not found",
             &response);
        break;
      }
      std::vector<const google::protobuf::FieldDescriptor*> extensions;
      pool->FindAllExtensions(type, &extensions);
      auto* numbers = response.mutable_all_extension_numbers_response();
      numbers->set_base_type_name(type->full_name());
      for (const auto* extension : extensions) {
        numbers->add_extension_number(extension->number());
      }
      break;
    }
    case ServerReflectionRequest::kListServices:
      for (const std::string& name : services_) {
        response.mutable_list_services_response()->add_service()->set_name(
            name);
      }
      break;
    default:
      Fail(kUnimplemented, "unknown reflection request", &response);
  }
  return response;
}

grpc::Status ReflectionV1::ServerReflectionInfo(
    grpc::ServerContext* context,
    grpc::ServerReaderWriter<ServerReflectionResponse, ServerReflectionRequest>*
        stream) {
  std::vector<std::string> sent;
  ServerReflectionRequest request;
  while (stream->Read(&request)) {
    if (!stream->Write(Answer(request, &sent))) break;
  }
  return grpc::Status::OK;
}

}  // namespace fleetmem::server
