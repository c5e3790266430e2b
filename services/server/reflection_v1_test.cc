#include "services/server/reflection_v1.h"

#include <string>
#include <vector>

#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/descriptor.pb.h"
#include "gtest/gtest.h"

namespace fleetmem::server {
namespace {

using grpc::reflection::v1::ServerReflectionRequest;
using grpc::reflection::v1::ServerReflectionResponse;

std::vector<std::string> FileNames(const ServerReflectionResponse& response) {
  std::vector<std::string> names;
  for (const std::string& bytes :
       response.file_descriptor_response().file_descriptor_proto()) {
    google::protobuf::FileDescriptorProto file;
    EXPECT_TRUE(file.ParseFromString(bytes));
    names.push_back(file.name());
  }
  return names;
}

TEST(ReflectionV1Test, ListsServicesAndSendsAFileWithItsImportsOnce) {
  (void)v1::MemoryTrace::descriptor();  // the API's file in the pool
  ReflectionV1 reflection(
      {"fleetmem.v1.MemoryService", "grpc.health.v1.Health"});
  std::vector<std::string> sent;
  ServerReflectionRequest list;
  list.set_list_services("*");
  ServerReflectionResponse listed = reflection.Answer(list, &sent);
  ASSERT_EQ(listed.list_services_response().service_size(), 2);
  EXPECT_EQ(listed.list_services_response().service(0).name(),
            "fleetmem.v1.MemoryService");
  EXPECT_EQ(listed.original_request().list_services(), "*");

  ServerReflectionRequest symbol;
  symbol.set_file_containing_symbol("fleetmem.v1.MemoryService");
  std::vector<std::string> files = FileNames(reflection.Answer(symbol, &sent));
  ASSERT_FALSE(files.empty());
  EXPECT_EQ(files.front(), "fleetmem/v1/memory.proto");
  // Its imports came with it (google/api/annotations.proto at least).
  EXPECT_GT(files.size(), 1u);
  // Asked again: the file, not its imports.
  EXPECT_EQ(FileNames(reflection.Answer(symbol, &sent)),
            std::vector<std::string>{"fleetmem/v1/memory.proto"});

  ServerReflectionRequest missing;
  missing.set_file_by_filename("no/such.proto");
  ServerReflectionResponse error = reflection.Answer(missing, &sent);
  EXPECT_EQ(error.error_response().error_code(),
            static_cast<int>(grpc::StatusCode::NOT_FOUND));
  EXPECT_NE(error.error_response().error_message().find("no/such.proto"),
            std::string::npos);
}

}  // namespace
}  // namespace fleetmem::server
