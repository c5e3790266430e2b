#include "services/core/feature_space.h"

#include <algorithm>
#include <cassert>
#include <cmath>

namespace fleetmem::core {
namespace {

// L2 norm in double precision (codes of 256+ floats lose little this way).
double Norm(std::span<const float> code) {
  double sum = 0.0;
  for (float v : code) sum += static_cast<double>(v) * v;
  return std::sqrt(sum);
}

}  // namespace

std::vector<float> NormalizedCode(std::span<const float> code) {
  std::vector<float> out(code.size());
  NormalizeInto(code, out);
  return out;
}

float UnitScale(std::span<const float> code) {
  const double norm = Norm(code);
  return norm > 0.0 ? static_cast<float>(1.0 / norm) : 0.0f;
}

double ScaledSquaredNorm(std::span<const float> vector, float scale) {
  double sum = 0.0;
  for (float v : vector) {
    const double scaled = static_cast<double>(scale) * v;
    sum += scaled * scaled;
  }
  return sum;
}

void NormalizeInto(std::span<const float> code, std::span<float> out) {
  assert(out.size() == code.size());
  const double norm = Norm(code);
  if (norm > 0.0) {
    for (size_t i = 0; i < code.size(); ++i) {
      out[i] = static_cast<float>(code[i] / norm);
    }
  } else {
    std::copy(code.begin(), code.end(), out.begin());
  }
}

Eigen::VectorXf FeatureSpatialCode(const MemoryTrace& trace,
                                   double spatial_scale_m) {
  const size_t dim = trace.code.size();
  Eigen::VectorXf out(static_cast<Eigen::Index>(dim + 3));
  const double norm = Norm(trace.code);
  for (size_t i = 0; i < dim; ++i) {
    out[static_cast<Eigen::Index>(i)] =
        norm > 0.0 ? static_cast<float>(trace.code[i] / norm) : 0.0f;
  }
  const double lambda = 1.0 / spatial_scale_m;
  out[static_cast<Eigen::Index>(dim)] =
      static_cast<float>(trace.place.x * lambda);
  out[static_cast<Eigen::Index>(dim + 1)] =
      static_cast<float>(trace.place.y * lambda);
  out[static_cast<Eigen::Index>(dim + 2)] =
      static_cast<float>(trace.place.z * lambda);
  return out;
}

float CodeDistance(std::span<const float> a, std::span<const float> b) {
  assert(a.size() == b.size());
  const size_t dim = std::min(a.size(), b.size());
  const double norm_a = Norm(a);
  const double norm_b = Norm(b);
  const double scale_a = norm_a > 0.0 ? 1.0 / norm_a : 0.0;
  const double scale_b = norm_b > 0.0 ? 1.0 / norm_b : 0.0;
  double sum = 0.0;
  for (size_t i = 0; i < dim; ++i) {
    const double d = a[i] * scale_a - b[i] * scale_b;
    sum += d * d;
  }
  return static_cast<float>(std::clamp(std::sqrt(sum), 0.0, 2.0));
}

}  // namespace fleetmem::core
