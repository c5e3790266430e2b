// What protobuf's JSON parser (3.21) lets through and a REST user should
// hear about: a key given twice in one object (it keeps the last), an
// array inside a repeated scalar field ("code": [[1, 2], [3]] read as
// [1, 2, 3]), and an enum value the API does not define (a number outside
// the enum is kept as is). CheckStrictJson refuses those before the parser
// runs; every other error is the parser's to report.
#ifndef FLEETMEM_SERVICES_HTTP_STRICT_JSON_H_
#define FLEETMEM_SERVICES_HTTP_STRICT_JSON_H_

#include <string_view>

#include "absl/status/status.h"
#include "google/protobuf/descriptor.h"

namespace fleetmem::http {

// OK, or INVALID_ARGUMENT naming the field path and what is wrong, for the
// JSON `text` of a message of `type`. Text that is not well-formed JSON is
// OK here (the parser says what is wrong with it).
absl::Status CheckStrictJson(std::string_view text,
                             const google::protobuf::Descriptor& type);

}  // namespace fleetmem::http

#endif  // FLEETMEM_SERVICES_HTTP_STRICT_JSON_H_
