// The OpenAPI 3 description of the HTTP port, made from the same tables the
// server serves: the REST routes (read from memory.proto's google.api.http
// options, RoutesFromProto) with their request and answer schemas made from
// the message descriptors under protobuf's canonical JSON mapping, and the
// server's other endpoints. Served at /openapi.json; never written by hand,
// so the description and the routes cannot drift apart.
#ifndef FLEETMEM_SERVICES_HTTP_OPENAPI_H_
#define FLEETMEM_SERVICES_HTTP_OPENAPI_H_

#include <string>
#include <vector>

#include "services/http/rest_gateway.h"

namespace fleetmem::http {

// An endpoint of the HTTP port outside the REST routes (/healthz, ...).
struct PlainEndpoint {
  const char* path;
  const char* content_type;  // of the answer
  const char* summary;
};

// The description (JSON). `version` is the server's.
std::string OpenApiJson(const std::vector<Route>& routes,
                        const std::vector<PlainEndpoint>& endpoints,
                        const std::string& version);

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_OPENAPI_H_
