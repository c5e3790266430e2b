// Protobuf text format for the files people write (the server's config, the
// credentials file): a parse error names line and column.
#ifndef FLEETMEM_SERVICES_COMMON_TEXT_FORMAT_H_
#define FLEETMEM_SERVICES_COMMON_TEXT_FORMAT_H_

#include <string_view>

#include "absl/status/status.h"
#include "google/protobuf/message.h"

namespace fleetmem {

// Parses `text` into `message` (cleared first). INVALID_ARGUMENT listing
// every complaint as "line L, column C: ..." (1-based), joined by "; ".
absl::Status ParseTextFormat(std::string_view text,
                             google::protobuf::Message* message);

}  // namespace fleetmem

#endif  // FLEETMEM_SERVICES_COMMON_TEXT_FORMAT_H_
