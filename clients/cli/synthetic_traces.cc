#include "clients/cli/synthetic_traces.h"

#include <cmath>
#include <numbers>
#include <random>

#include "absl/strings/str_cat.h"

namespace fleetmem::cli {
namespace {

constexpr int kPlacesPerAnchor = 10;
constexpr double kPlaceSpacingM = 5.0;
constexpr double kPositionNoiseM = 1.0;
constexpr double kDomainShift = 0.3;
constexpr double kCodeNoise = 0.2;
constexpr int64_t kStartTimeNs = 1'700'000'000'000'000'000;
constexpr int64_t kNsPerSecond = 1'000'000'000;
constexpr const char* kDomains[] = {"summer", "fall", "winter", "spring"};
constexpr int kDomainCount = 4;

using Vector = std::vector<double>;

Vector RandomVector(int dimension, double scale, std::mt19937_64& rng) {
  std::normal_distribution<double> normal(0.0, scale);
  Vector vector(dimension);
  for (double& value : vector) value = normal(rng);
  return vector;
}

}  // namespace

std::vector<v1::MemoryTrace> GenerateSyntheticTraces(
    const SyntheticTraceOptions& options) {
  std::vector<v1::MemoryTrace> traces;
  if (options.robots <= 0 || options.per_robot <= 0 || options.dimension <= 0) {
    return traces;
  }
  std::mt19937_64 rng(options.seed);
  const int dimension = options.dimension;
  const int anchors =
      (options.per_robot + kPlacesPerAnchor - 1) / kPlacesPerAnchor;
  std::vector<Vector> anchor_codes;
  for (int i = 0; i < anchors; ++i) {
    anchor_codes.push_back(RandomVector(dimension, 1.0, rng));
  }
  std::vector<Vector> domain_shifts;
  for (int i = 0; i < kDomainCount; ++i) {
    domain_shifts.push_back(RandomVector(dimension, kDomainShift, rng));
  }
  const double loop_radius_m =
      options.per_robot * kPlaceSpacingM / (2 * std::numbers::pi);
  std::normal_distribution<double> position_noise(0.0, kPositionNoiseM);
  std::normal_distribution<double> code_noise(0.0, kCodeNoise);
  std::uniform_real_distribution<double> unit(0.0, 1.0);

  traces.reserve(static_cast<size_t>(options.robots) * options.per_robot);
  for (int robot = 0; robot < options.robots; ++robot) {
    const int domain = robot % kDomainCount;
    for (int place = 0; place < options.per_robot; ++place) {
      v1::MemoryTrace& trace = traces.emplace_back();
      trace.set_robot_id(absl::StrCat("robot-", robot + 1));
      trace.set_seq(place + 1);
      trace.set_domain(kDomains[domain]);
      trace.set_encoder_version(options.encoder_version);
      trace.set_timestamp_ns(kStartTimeNs + robot * 86'400 * kNsPerSecond +
                             place * kNsPerSecond);

      const int anchor = place / kPlacesPerAnchor;
      const double t =
          static_cast<double>(place % kPlacesPerAnchor) / kPlacesPerAnchor;
      const Vector& from = anchor_codes[anchor];
      const Vector& to = anchor_codes[(anchor + 1) % anchors];
      Vector code(dimension);
      double norm_squared = 0;
      for (int d = 0; d < dimension; ++d) {
        code[d] = (1 - t) * from[d] + t * to[d] + domain_shifts[domain][d] +
                  code_noise(rng);
        norm_squared += code[d] * code[d];
      }
      const double norm = std::sqrt(norm_squared);
      for (double value : code) {
        trace.add_code(static_cast<float>(norm > 0 ? value / norm : 0));
      }

      const double angle = 2 * std::numbers::pi * place / options.per_robot;
      v1::Pose* pose = trace.mutable_pose();
      pose->set_x(loop_radius_m * std::cos(angle) + position_noise(rng));
      pose->set_y(loop_radius_m * std::sin(angle) + position_noise(rng));
      pose->set_yaw(angle + std::numbers::pi / 2);

      const float external = static_cast<float>(unit(rng));
      const float internal = static_cast<float>(0.5 * unit(rng));
      trace.set_reward_external(external);
      trace.set_reward_internal(internal);
      trace.set_reward(external + internal);
    }
  }
  return traces;
}

}  // namespace fleetmem::cli
