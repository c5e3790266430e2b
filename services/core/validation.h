// Input rules for traces and identifiers, shared by the server and clients.
// Every error is INVALID_ARGUMENT with a message naming the field.
#ifndef FLEETMEM_SERVICES_CORE_VALIDATION_H_
#define FLEETMEM_SERVICES_CORE_VALIDATION_H_

#include <cstddef>
#include <span>
#include <string_view>

#include "absl/status/status.h"
#include "services/core/types.h"

namespace fleetmem::core {

inline constexpr size_t kMaxIdLength = 128;
inline constexpr size_t kMaxDomainLength = 64;
inline constexpr size_t kMaxEncoderVersionLength = 64;
inline constexpr size_t kMaxCodeDimension = 65536;
inline constexpr size_t kMaxAttachmentBytes = 16384;
// A code's Euclidean norm, unless the code is all zeros: what single-precision
// distance arithmetic holds. Squared norms and dot products of codes are
// summed in float32 (up to ~3.4e38): a norm of 1e18 leaves a wide margin at
// any dimension, while codes of ±3e38 overflow and are then found by nothing
// (or displace every other code). Below 1e-18 a code's unit vector is lost
// to underflow (values like 1e-45 are denormal). Real encoders' codes have
// norms near 1 (0.01 .. 1e6 covers every code the project makes).
inline constexpr double kMaxCodeNorm = 1e18;
inline constexpr double kMinCodeNorm = 1e-18;
// Largest |x|, |y|, |z| of a place, in metres: far beyond any map frame, and
// small enough that the feature-spatial code (single precision) stays finite.
inline constexpr double kMaxCoordinateM = 1e9;

// Fleet and robot ids: 1..128 characters of [A-Za-z0-9._:-]. `what` names the
// field in the message ("fleet_id", "traces[3].robot_id").
absl::Status ValidateId(std::string_view what, std::string_view id);

// Every value finite; size in 1..kMaxCodeDimension; the norm, computed in
// double, within [kMinCodeNorm, kMaxCodeNorm] unless every value is 0 (a
// black frame's code; kept as before).
absl::Status ValidateCode(std::string_view what, std::span<const float> code);

// What the fleet expects of a trace; 0 / empty means "not fixed yet".
struct TraceShape {
  size_t code_dimension = 0;
  std::string_view encoder_version;
  // Names the fleet in messages (`fleet "f1" uses 256`); may be empty.
  std::string_view fleet_id;
};

// Checks ids, code, place (finite, |x|, |y|, |z| <= kMaxCoordinateM), rewards
// (finite, reward >= 0), domain and encoder version lengths, and the fleet's
// dimension and encoder version.
absl::Status ValidateTrace(std::string_view what, const MemoryTrace& trace,
                           const TraceShape& shape);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_VALIDATION_H_
