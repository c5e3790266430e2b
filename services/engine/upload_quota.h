// Upload quotas of the engine: rates per fleet and per robot (traces and
// bytes per second, token buckets), stored traces per fleet, fleets per
// server and the code dimension. Every limit that refuses names itself in
// a RESOURCE_EXHAUSTED status and is counted (per fleet and limit) for the
// metrics. Thread-safe; the clock is injected.
#ifndef FLEETMEM_SERVICES_ENGINE_UPLOAD_QUOTA_H_
#define FLEETMEM_SERVICES_ENGINE_UPLOAD_QUOTA_H_

#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <span>
#include <string>
#include <string_view>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "services/core/types.h"

namespace fleetmem::engine {

// 0 means unlimited for every field.
struct QuotaOptions {
  // Traces accepted into one fleet per second (over all its robots).
  double fleet_traces_per_second = 0;
  // Bytes of traces (see TraceBytes) per fleet per second.
  double fleet_bytes_per_second = 0;
  // Traces / bytes from one robot of a fleet per second.
  double robot_traces_per_second = 0;
  double robot_bytes_per_second = 0;
  // A bucket holds this many seconds of its rate, so short bursts pass.
  double burst_seconds = 2.0;
  // Traces a fleet may hold (static memory + pending). The static memory is
  // bounded by K_max x N_max; pending traces grow with the number of robots.
  uint64_t max_traces_per_fleet = 1'000'000;
  // Fleets one server holds.
  uint64_t max_fleets = 1000;
  // Largest code dimension a fleet may use.
  uint32_t max_code_dimension = 4096;
  // An upload to a fleet that does not exist creates it (with the server's
  // settings); false: only CreateFleet creates fleets, and such an upload
  // is refused, NOT_FOUND.
  bool auto_create_fleets = true;
};

absl::Status ValidateQuotaOptions(const QuotaOptions& options);

// Approximate stored size of a trace: its code, ids and fixed fields.
size_t TraceBytes(const core::MemoryTrace& trace);

class UploadQuota {
 public:
  // `now_seconds` is a monotonic clock in seconds.
  UploadQuota(QuotaOptions options, std::function<double()> now_seconds);

  const QuotaOptions& options() const { return options_; }

  // NOT_FOUND (nothing stored) for an upload that would create a fleet on
  // a server that creates fleets by CreateFleet only.
  absl::Status AdmitCreationByUpload(std::string_view fleet_id) const;
  // RESOURCE_EXHAUSTED "limit max_fleets ..." if a new fleet would exceed it.
  absl::Status AdmitNewFleet(std::string_view fleet_id, size_t fleets);
  // RESOURCE_EXHAUSTED "limit max_code_dimension ..." for a larger code.
  absl::Status AdmitDimension(std::string_view fleet_id, size_t dimension);
  // RESOURCE_EXHAUSTED "limit max_traces_per_fleet ..." if `held + adding`
  // would exceed it.
  absl::Status AdmitStored(std::string_view fleet_id, uint64_t held,
                           uint64_t adding);
  // The rate limits for a message of `traces` (all of them, duplicates too:
  // they cost the server the same work): all-or-nothing, so a refused
  // message consumes nothing. RESOURCE_EXHAUSTED naming the limit, the fleet
  // or robot and when to retry.
  absl::Status AdmitRates(std::string_view fleet_id,
                          std::span<const core::MemoryTrace> traces);

  // Refusals so far of `fleet_id`, by limit name.
  std::map<std::string, uint64_t> Rejections(std::string_view fleet_id) const;

 private:
  struct Bucket {
    double tokens = 0;
    double updated = -1;  // never
  };
  // Refills `bucket` at `rate` to now; true if it holds `need` tokens (or is
  // full, for a message larger than the bucket).
  bool Refill(Bucket& bucket, double rate, double need, double now) const;
  absl::Status Refuse(std::string_view fleet_id, std::string_view limit,
                      std::string message) ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  const QuotaOptions options_;
  const std::function<double()> now_seconds_;
  mutable absl::Mutex mu_;
  // By "fleet" and "fleet\0robot", traces and bytes.
  absl::flat_hash_map<std::string, Bucket> trace_buckets_ ABSL_GUARDED_BY(mu_);
  absl::flat_hash_map<std::string, Bucket> byte_buckets_ ABSL_GUARDED_BY(mu_);
  // fleet -> limit -> refusals.
  absl::flat_hash_map<std::string, std::map<std::string, uint64_t>> rejections_
      ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_UPLOAD_QUOTA_H_
