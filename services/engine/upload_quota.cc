#include "services/engine/upload_quota.h"

#include <algorithm>
#include <cmath>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "services/core/absl_view.h"

namespace fleetmem::engine {
absl::Status ValidateQuotaOptions(const QuotaOptions& options) {
  const std::pair<const char*, double> rates[] = {
      {"fleet_traces_per_second", options.fleet_traces_per_second},
      {"fleet_bytes_per_second", options.fleet_bytes_per_second},
      {"robot_traces_per_second", options.robot_traces_per_second},
      {"robot_bytes_per_second", options.robot_bytes_per_second},
  };
  for (const auto& [name, rate] : rates) {
    if (!std::isfinite(rate) || rate < 0) {
      return absl::InvalidArgumentError(
          absl::StrCat("limits.", name, ": must be finite and >= 0"));
    }
  }
  if (!std::isfinite(options.burst_seconds) || options.burst_seconds <= 0) {
    return absl::InvalidArgumentError("limits.burst_seconds: must be > 0");
  }
  return absl::OkStatus();
}

size_t TraceBytes(const core::MemoryTrace& trace) {
  return trace.code.size() * sizeof(float) + trace.robot_id.size() +
         trace.domain.size() + trace.encoder_version.size() + 64;
}

UploadQuota::UploadQuota(QuotaOptions options,
                         std::function<double()> now_seconds)
    : options_(options), now_seconds_(std::move(now_seconds)) {}

absl::Status UploadQuota::Refuse(std::string_view fleet_id,
                                 std::string_view limit, std::string message) {
  ++rejections_[std::string(fleet_id)][std::string(limit)];
  return absl::ResourceExhaustedError(
      absl::StrCat("limit ", V(limit), " ", message));
}

absl::Status UploadQuota::AdmitCreationByUpload(
    std::string_view fleet_id) const {
  if (options_.auto_create_fleets) return absl::OkStatus();
  return absl::NotFoundError(absl::StrCat(
      "fleet \"", V(fleet_id),
      "\" does not exist and this server makes fleets by CreateFleet only "
      "(auto_create_fleets: false); nothing was stored"));
}

absl::Status UploadQuota::AdmitNewFleet(std::string_view fleet_id,
                                        size_t fleets) {
  if (options_.max_fleets == 0 || fleets < options_.max_fleets) {
    return absl::OkStatus();
  }
  absl::MutexLock lock(&mu_);
  return Refuse(
      fleet_id, "max_fleets",
      absl::StrCat("(", options_.max_fleets, ") reached: fleet \"", V(fleet_id),
                   "\" is not created; nothing was stored"));
}

absl::Status UploadQuota::AdmitDimension(std::string_view fleet_id,
                                         size_t dimension) {
  if (options_.max_code_dimension == 0 ||
      dimension <= options_.max_code_dimension) {
    return absl::OkStatus();
  }
  absl::MutexLock lock(&mu_);
  return Refuse(fleet_id, "max_code_dimension",
                absl::StrCat("(", options_.max_code_dimension,
                             ") exceeded: codes of dimension ", dimension,
                             "; nothing was stored"));
}

absl::Status UploadQuota::AdmitStored(std::string_view fleet_id, uint64_t held,
                                      uint64_t adding) {
  if (options_.max_traces_per_fleet == 0 ||
      held + adding <= options_.max_traces_per_fleet) {
    return absl::OkStatus();
  }
  absl::MutexLock lock(&mu_);
  return Refuse(fleet_id, "max_traces_per_fleet",
                absl::StrCat("(", options_.max_traces_per_fleet,
                             ") reached: fleet \"", V(fleet_id), "\" holds ",
                             held, " traces and this upload ", "adds ", adding,
                             "; nothing was stored (consolidation and "
                             "forgetting make room)"));
}

bool UploadQuota::Refill(Bucket& bucket, double rate, double need,
                         double now) const {
  const double capacity = rate * options_.burst_seconds;
  if (bucket.updated < 0) {
    bucket.tokens = capacity;
  } else {
    bucket.tokens =
        std::min(capacity, bucket.tokens + (now - bucket.updated) * rate);
  }
  bucket.updated = now;
  return bucket.tokens >= std::min(need, capacity);
}

absl::Status UploadQuota::AdmitRates(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces) {
  const bool any = options_.fleet_traces_per_second > 0 ||
                   options_.fleet_bytes_per_second > 0 ||
                   options_.robot_traces_per_second > 0 ||
                   options_.robot_bytes_per_second > 0;
  if (!any || traces.empty()) return absl::OkStatus();
  // Demand per robot and for the fleet.
  std::map<std::string, std::pair<double, double>> robots;
  double fleet_traces = 0, fleet_bytes = 0;
  for (const core::MemoryTrace& trace : traces) {
    const double bytes = static_cast<double>(TraceBytes(trace));
    auto& [count, size] = robots[trace.robot_id];
    count += 1;
    size += bytes;
    fleet_traces += 1;
    fleet_bytes += bytes;
  }
  struct Demand {
    absl::flat_hash_map<std::string, Bucket>* buckets;
    std::string key;
    double rate;
    double need;
    const char* limit;
    std::string who;
    const char* unit;
  };
  const std::string fleet(fleet_id);
  std::vector<Demand> demands;
  if (options_.fleet_traces_per_second > 0) {
    demands.push_back({&trace_buckets_, fleet, options_.fleet_traces_per_second,
                       fleet_traces, "fleet_traces_per_second",
                       absl::StrCat("fleet \"", fleet, "\""), "traces"});
  }
  if (options_.fleet_bytes_per_second > 0) {
    demands.push_back({&byte_buckets_, fleet, options_.fleet_bytes_per_second,
                       fleet_bytes, "fleet_bytes_per_second",
                       absl::StrCat("fleet \"", fleet, "\""), "bytes"});
  }
  for (const auto& [robot, need] : robots) {
    const std::string key = absl::StrCat(fleet, std::string(1, '\0'), robot);
    const std::string who =
        absl::StrCat("robot \"", robot, "\" in fleet \"", fleet, "\"");
    if (options_.robot_traces_per_second > 0) {
      demands.push_back({&trace_buckets_, key, options_.robot_traces_per_second,
                         need.first, "robot_traces_per_second", who, "traces"});
    }
    if (options_.robot_bytes_per_second > 0) {
      demands.push_back({&byte_buckets_, key, options_.robot_bytes_per_second,
                         need.second, "robot_bytes_per_second", who, "bytes"});
    }
  }
  const double now = now_seconds_();
  absl::MutexLock lock(&mu_);
  for (Demand& demand : demands) {
    Bucket& bucket = (*demand.buckets)[demand.key];
    if (!Refill(bucket, demand.rate, demand.need, now)) {
      const double wait =
          (std::min(demand.need, demand.rate * options_.burst_seconds) -
           bucket.tokens) /
          demand.rate;
      return Refuse(
          fleet_id, demand.limit,
          absl::StrFormat("(%g %s/s) exceeded by %s: this message needs "
                          "%.0f; retry in %.2f s; nothing was stored",
                          demand.rate, demand.unit, demand.who, demand.need,
                          wait));
    }
  }
  for (Demand& demand : demands) {
    (*demand.buckets)[demand.key].tokens -= demand.need;
  }
  return absl::OkStatus();
}

std::map<std::string, uint64_t> UploadQuota::Rejections(
    std::string_view fleet_id) const {
  absl::MutexLock lock(&mu_);
  auto it = rejections_.find(std::string(fleet_id));
  return it == rejections_.end() ? std::map<std::string, uint64_t>()
                                 : it->second;
}

}  // namespace fleetmem::engine
