#include "services/core/validation.h"

#include <cmath>
#include <span>
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

// ValidateCode's test without its message: every value finite and the
// norm in range (or 0). Eight independent sums, so that the loop is not
// one long chain of dependent additions (a code of every upload passes
// here: it was 11 % of the server's time acknowledging a burst,
// bench/ack_profile.sh); a
// non-finite value makes the sum NaN or infinite.
bool CodeInRange(std::span<const float> code) {
  double sums[8] = {};
  size_t i = 0;
  for (; i + 8 <= code.size(); i += 8) {
    for (size_t j = 0; j < 8; ++j) {
      sums[j] += static_cast<double>(code[i + j]) * code[i + j];
    }
  }
  for (; i < code.size(); ++i) {
    sums[0] += static_cast<double>(code[i]) * code[i];
  }
  const double squared = ((sums[0] + sums[1]) + (sums[2] + sums[3])) +
                         ((sums[4] + sums[5]) + (sums[6] + sums[7]));
  if (!std::isfinite(squared)) return false;
  if (squared == 0) return true;
  const double norm = std::sqrt(squared);
  return norm <= kMaxCodeNorm && norm >= kMinCodeNorm;
}

// `status` (a check's of a field named without the trace) for the field of
// `what`: its message starts with the field's name.
absl::Status OfTrace(std::string_view what, const absl::Status& status) {
  if (status.ok()) return status;
  return Invalid(absl::StrCat(V(what), ".", status.message()));
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
  if (CodeInRange(code)) return absl::OkStatus();
  // Which value, or what norm: the message.
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
    return Invalid(
        absl::StrCat(V(what), " has norm ", norm, " (largest value: [", largest,
                     "] = ", code[largest], "); a code's norm must be in ",
                     kMinCodeNorm, " .. ", kMaxCodeNorm,
                     " (or the code all zeros) for single-precision "
                     "distances to hold it: scale the codes"));
  }
  return absl::OkStatus();
}

absl::Status ValidateTrace(std::string_view what, const MemoryTrace& trace,
                           const TraceShape& shape) {
  // The fields' names are joined to `what` only for a message: this runs
  // for every trace uploaded.
  if (absl::Status s = OfTrace(what, ValidateId("robot_id", trace.robot_id));
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
  if (absl::Status s = OfTrace(what, ValidateCode("code", trace.code));
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
