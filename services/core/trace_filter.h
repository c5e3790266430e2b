// Which traces of a fleet a call concerns: DeleteTraces' selection (and the
// filter the reads will take). A trace matches when it meets every
// criterion that is set; a filter with none set matches every trace.
// Pure: no I/O.
#ifndef FLEETMEM_SERVICES_CORE_TRACE_FILTER_H_
#define FLEETMEM_SERVICES_CORE_TRACE_FILTER_H_

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/status.h"
#include "services/core/types.h"

namespace fleetmem::core {

struct TraceFilter {
  // One robot's traces; empty: every robot's.
  std::string robot_id;
  // Traces of this appearance domain; empty: every domain.
  std::string domain;
  // The robot's seqs from `seq_first` through `seq_last` (both inclusive;
  // unset: unbounded on that side). Only with `robot_id`: seqs are per
  // robot.
  std::optional<uint64_t> seq_first;
  std::optional<uint64_t> seq_last;
  // Observation times (MemoryTrace::timestamp_ns) in [time_from_ns,
  // time_to_ns); unset: unbounded on that side.
  std::optional<int64_t> time_from_ns;
  std::optional<int64_t> time_to_ns;

  // True if no criterion is set (every trace matches).
  bool selects_all() const {
    return robot_id.empty() && domain.empty() && !seq_first && !seq_last &&
           !time_from_ns && !time_to_ns;
  }
  bool Matches(const MemoryTrace& trace) const;
};

// Which traces a read considers (QueryPlace's filter): those that meet
// every criterion set.
struct ReadFilter {
  // Any of these robots' traces; empty: every robot's.
  std::vector<std::string> robot_ids;
  // Any of these domains; empty: every domain.
  std::vector<std::string> domains;
  // Observation times in [time_from_ns, time_to_ns).
  std::optional<int64_t> time_from_ns;
  std::optional<int64_t> time_to_ns;
  // Traces of this encoder version; empty: any.
  std::string encoder_version;

  bool selects_all() const {
    return robot_ids.empty() && domains.empty() && !time_from_ns &&
           !time_to_ns && encoder_version.empty();
  }
  bool Matches(const MemoryTrace& trace) const;
};

// INVALID_ARGUMENT naming the field: a malformed robot id, more than 1,000
// robots or domains, an empty time range.
absl::Status ValidateReadFilter(std::string_view what,
                                const ReadFilter& filter);

// INVALID_ARGUMENT naming the field (`what`.robot_id, ...; the field alone
// for an empty `what`) when a set id or
// domain is malformed, a seq range has no robot, or a range is empty
// (first > last, from >= to).
absl::Status ValidateTraceFilter(std::string_view what,
                                 const TraceFilter& filter);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_TRACE_FILTER_H_
