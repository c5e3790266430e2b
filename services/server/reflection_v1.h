// grpc.reflection.v1.ServerReflection (issue 48: gRPC 1.51's reflection
// library serves only the older grpc.reflection.v1alpha; grpcurl, Postman
// and grpcui ask v1 first). Answers from the process's generated descriptor
// pool, like v1alpha: a file with every file it imports (each once per
// stream), the file of a symbol or an extension, a type's extension
// numbers, and the services of this server. Registered where v1alpha is
// (auth off, or reflection_with_auth: docs/security.md).
#ifndef FLEETMEM_SERVICES_SERVER_REFLECTION_V1_H_
#define FLEETMEM_SERVICES_SERVER_REFLECTION_V1_H_

#include <string>
#include <vector>

#include "grpc/reflection/v1/reflection.grpc.pb.h"

namespace fleetmem::server {

class ReflectionV1 final
    : public grpc::reflection::v1::ServerReflection::Service {
 public:
  // `services`: the full names ListServices answers.
  explicit ReflectionV1(std::vector<std::string> services);

  grpc::Status ServerReflectionInfo(
      grpc::ServerContext* context,
      grpc::ServerReaderWriter<grpc::reflection::v1::ServerReflectionResponse,
                               grpc::reflection::v1::ServerReflectionRequest>*
          stream) override;

  // One request's answer (`sent`: files this stream has sent already).
  grpc::reflection::v1::ServerReflectionResponse Answer(
      const grpc::reflection::v1::ServerReflectionRequest& request,
      std::vector<std::string>* sent) const;

 private:
  std::vector<std::string> services_;
};

}  // namespace fleetmem::server

#endif  // FLEETMEM_SERVICES_SERVER_REFLECTION_V1_H_
