#include "services/core/trace_filter.h"

#include <algorithm>

#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"
#include "services/core/validation.h"

namespace fleetmem::core {

bool TraceFilter::Matches(const MemoryTrace& trace) const {
  if (!robot_id.empty() && trace.robot_id != robot_id) return false;
  if (!domain.empty() && trace.domain != domain) return false;
  if (seq_first && trace.seq < *seq_first) return false;
  if (seq_last && trace.seq > *seq_last) return false;
  if (time_from_ns && trace.timestamp_ns < *time_from_ns) return false;
  if (time_to_ns && trace.timestamp_ns >= *time_to_ns) return false;
  return true;
}

absl::Status ValidateTraceFilter(std::string_view what,
                                 const TraceFilter& filter) {
  // `what`.field, or the field alone for an unnamed filter.
  auto field = [what](std::string_view name) {
    return what.empty() ? std::string(name)
                        : absl::StrCat(V(what), ".", V(name));
  };
  if (!filter.robot_id.empty()) {
    absl::Status status = ValidateId(field("robot_id"), filter.robot_id);
    if (!status.ok()) return status;
  }
  if (filter.domain.size() > kMaxDomainLength) {
    return absl::InvalidArgumentError(
        absl::StrCat(field("domain"), " is ", filter.domain.size(),
                     " characters; at most ", kMaxDomainLength));
  }
  if ((filter.seq_first || filter.seq_last) && filter.robot_id.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        field("seq_first"),
        ", seq_last: a seq range needs robot_id (seqs are per robot)"));
  }
  if (filter.seq_first && filter.seq_last &&
      *filter.seq_first > *filter.seq_last) {
    return absl::InvalidArgumentError(
        absl::StrCat(field("seq_first"), " ", *filter.seq_first,
                     " is after seq_last ", *filter.seq_last));
  }
  if (filter.time_from_ns && filter.time_to_ns &&
      *filter.time_from_ns >= *filter.time_to_ns) {
    return absl::InvalidArgumentError(absl::StrCat(
        field("time_from_ns"), " ", *filter.time_from_ns,
        " is not before time_to_ns ", *filter.time_to_ns, " (an empty range)"));
  }
  return absl::OkStatus();
}

bool ReadFilter::Matches(const MemoryTrace& trace) const {
  if (!robot_ids.empty() && std::find(robot_ids.begin(), robot_ids.end(),
                                      trace.robot_id) == robot_ids.end()) {
    return false;
  }
  if (!domains.empty() && std::find(domains.begin(), domains.end(),
                                    trace.domain) == domains.end()) {
    return false;
  }
  if (time_from_ns && trace.timestamp_ns < *time_from_ns) return false;
  if (time_to_ns && trace.timestamp_ns >= *time_to_ns) return false;
  if (!encoder_version.empty() && trace.encoder_version != encoder_version) {
    return false;
  }
  return true;
}

absl::Status ValidateReadFilter(std::string_view what,
                                const ReadFilter& filter) {
  constexpr size_t kMaxNamed = 1000;
  if (filter.robot_ids.size() > kMaxNamed ||
      filter.domains.size() > kMaxNamed) {
    return absl::InvalidArgumentError(
        absl::StrCat(V(what), ": at most ", kMaxNamed, " robots and ",
                     kMaxNamed, " domains (", filter.robot_ids.size(), " and ",
                     filter.domains.size(), " given)"));
  }
  for (size_t i = 0; i < filter.robot_ids.size(); ++i) {
    absl::Status status = ValidateId(
        absl::StrCat(V(what), ".robot_ids[", i, "]"), filter.robot_ids[i]);
    if (!status.ok()) return status;
  }
  if (filter.time_from_ns && filter.time_to_ns &&
      *filter.time_from_ns >= *filter.time_to_ns) {
    return absl::InvalidArgumentError(
        absl::StrCat(V(what), ": time_from_ns ", *filter.time_from_ns,
                     " is not before time_to_ns ", *filter.time_to_ns));
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::core
