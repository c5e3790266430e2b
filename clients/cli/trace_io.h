// Reading and writing the CLI's JSON inputs: memory traces as JSON Lines
// (one fleetmem.v1.MemoryTrace per line, protobuf JSON mapping) and query
// codes.
#ifndef FLEETMEM_CLIENTS_CLI_TRACE_IO_H_
#define FLEETMEM_CLIENTS_CLI_TRACE_IO_H_

#include <istream>
#include <ostream>
#include <span>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "fleetmem/v1/memory.pb.h"

namespace fleetmem::cli {

// Reads one MemoryTrace per line; blank lines are skipped. Unknown fields are
// errors. INVALID_ARGUMENT names the line of the first bad trace.
absl::StatusOr<std::vector<v1::MemoryTrace>> ReadTracesJsonl(std::istream& in);

// Reads one RewardUpdate per line, as ReadTracesJsonl.
absl::StatusOr<std::vector<v1::RewardUpdate>> ReadRewardUpdatesJsonl(
    std::istream& in);

// Writes one MemoryTrace per line (compact protobuf JSON).
absl::Status WriteTracesJsonl(std::span<const v1::MemoryTrace> traces,
                              std::ostream& out);

// Parses a query given as JSON: a bare array of numbers, or an object with a
// "code" array, such as a QueryPlaceRequest or a MemoryTrace line (fields a
// QueryPlaceRequest does not have are ignored; its k, near and radiusM are
// kept). INVALID_ARGUMENT when there is no code.
absl::StatusOr<v1::QueryPlaceRequest> ParseQueryJson(absl::string_view json);

}  // namespace fleetmem::cli

#endif  // FLEETMEM_CLIENTS_CLI_TRACE_IO_H_
