#include "services/core/validation.h"

#include <cmath>
#include <string>

#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::core {
namespace {

// Values quoted in messages are escaped and cut to a readable length.
std::string Quote(std::string_view value) {
  constexpr size_t kShown = 40;
  if (value.size() <= kShown)
    return absl::StrCat("\"", absl::CHexEscape(V(value)), "\"");
  return absl::StrCat("\"", absl::CHexEscape(V(value.substr(0, kShown))),
                      "\"... (", value.size(), " characters)");
}

bool IsIdChar(char c) {
  return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') ||
         (c >= '0' && c <= '9') || c == '.' || c == '_' || c == ':' || c == '-';
}

absl::Status Invalid(std::string message) {
  return absl::InvalidArgumentError(std::move(message));
}

absl::Status CheckFinite(std::string_view what, std::string_view field,
                         double value) {
  if (std::isfinite(value)) return absl::OkStatus();
  return Invalid(
      absl::StrCat(V(what), ".", V(field), " is ", value, "; must be finite"));
}

absl::Status CheckLength(std::string_view what, std::string_view field,
                         std::string_view value, size_t max_length) {
  if (value.size() <= max_length) return absl::OkStatus();
  return Invalid(absl::StrCat(V(what), ".", V(field), " ", Quote(value),
                              " has ", value.size(), " characters; at most ",
                              max_length, " allowed"));
}

std::string FleetName(std::string_view fleet_id) {
  return fleet_id.empty() ? "the fleet"
                          : absl::StrCat("fleet ", Quote(fleet_id));
}

}  // namespace

absl::Status ValidateId(std::string_view what, std::string_view id) {
  if (id.empty()) return Invalid(absl::StrCat(V(what), " is empty"));
  if (id.size() > kMaxIdLength) {
    return Invalid(absl::StrCat(V(what), " ", Quote(id), " has ", id.size(),
                                " characters; at most ", kMaxIdLength,
                                " allowed"));
  }
  for (size_t i = 0; i < id.size(); ++i) {
    if (!IsIdChar(id[i])) {
      return Invalid(
          absl::StrCat(V(what), " ", Quote(id), " has invalid character '",
                       absl::CHexEscape(V(id.substr(i, 1))), "' at position ",
                       i, "; allowed: A-Z a-z 0-9 . _ : -"));
    }
  }
  return absl::OkStatus();
}

absl::Status ValidateCode(std::string_view what, std::span<const float> code) {
  if (code.empty()) return Invalid(absl::StrCat(V(what), " is empty"));
  if (code.size() > kMaxCodeDimension) {
    return Invalid(absl::StrCat(V(what), " has dimension ", code.size(),
                                "; at most ", kMaxCodeDimension, " allowed"));
  }
  double squared = 0;
  size_t largest = 0;
  for (size_t i = 0; i < code.size(); ++i) {
    if (!std::isfinite(code[i])) {
      return Invalid(
          absl::StrCat(V(what), "[", i, "] is ", code[i], "; must be finite"));
    }
    squared += static_cast<double>(code[i]) * code[i];
    if (std::fabs(code[i]) > std::fabs(code[largest])) largest = i;
  }
  if (squared == 0) return absl::OkStatus();
  const double norm = std::sqrt(squared);
  if (norm > kMaxCodeNorm || norm < kMinCodeNorm) {
    return Invalid(absl::StrCat(
        V(what), " has norm ", norm, " (largest value: [", largest, "] = ",
        code[largest], "); a code's norm must be in ", kMinCodeNorm, " .. ",
        kMaxCodeNorm, " (or the code all zeros) for single-precision "
        "distances to hold it: scale the codes"));
  }
  return absl::OkStatus();
}

absl::Status ValidateTrace(std::string_view what, const MemoryTrace& trace,
                           const TraceShape& shape) {
  if (absl::Status s =
          ValidateId(absl::StrCat(V(what), ".robot_id"), trace.robot_id);
      !s.ok()) {
    return s;
  }
  if (absl::Status s =
          CheckLength(what, "domain", trace.domain, kMaxDomainLength);
      !s.ok()) {
    return s;
  }
  if (absl::Status s =
          CheckLength(what, "encoder_version", trace.encoder_version,
                      kMaxEncoderVersionLength);
      !s.ok()) {
    return s;
  }
  if (trace.attachment.size() > kMaxAttachmentBytes) {
    return Invalid(absl::StrCat(V(what), ".attachment has ",
                                trace.attachment.size(), " bytes; at most ",
                                kMaxAttachmentBytes, " allowed"));
  }
  if (absl::Status s = ValidateCode(absl::StrCat(V(what), ".code"), trace.code);
      !s.ok()) {
    return s;
  }
  if (shape.code_dimension != 0 && trace.code.size() != shape.code_dimension) {
    return Invalid(absl::StrCat(
        V(what), ".code has dimension ", trace.code.size(), " but ",
        FleetName(shape.fleet_id), " uses ", shape.code_dimension));
  }
  if (!shape.encoder_version.empty() &&
      trace.encoder_version != shape.encoder_version) {
    return Invalid(absl::StrCat(
        V(what), ".encoder_version is ", Quote(trace.encoder_version), " but ",
        FleetName(shape.fleet_id), " uses ", Quote(shape.encoder_version)));
  }
  const std::pair<std::string_view, double> values[] = {
      {"place.x", trace.place.x},
      {"place.y", trace.place.y},
      {"place.z", trace.place.z},
      {"place.yaw", trace.place.yaw},
      {"reward", trace.reward},
      {"reward_external", trace.reward_external},
      {"reward_internal", trace.reward_internal},
  };
  for (const auto& [field, value] : values) {
    if (absl::Status s = CheckFinite(what, field, value); !s.ok()) return s;
  }
  if (trace.reward < 0.0f) {
    return Invalid(
        absl::StrCat(V(what), ".reward is ", trace.reward, "; must be >= 0"));
  }
  const std::pair<std::string_view, double> coordinates[] = {
      {"place.x", trace.place.x},
      {"place.y", trace.place.y},
      {"place.z", trace.place.z},
  };
  for (const auto& [field, value] : coordinates) {
    if (std::abs(value) > kMaxCoordinateM) {
      return Invalid(absl::StrCat(V(what), ".", V(field), " is ", value,
                                  "; must be within +-", kMaxCoordinateM,
                                  " m"));
    }
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::core
