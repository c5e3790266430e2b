// Feature-spatial codes c_k = [z_k / |z_k|, lambda * p_k] (Alg. 1 line 1) and
// code distances. memory.md: codes are L2-normalised, lambda = 1/scale_m.
#ifndef FLEETMEM_SERVICES_CORE_FEATURE_SPACE_H_
#define FLEETMEM_SERVICES_CORE_FEATURE_SPACE_H_

#include <span>
#include <vector>

#include "Eigen/Core"
#include "services/core/types.h"

namespace fleetmem::core {

// `code` scaled to unit L2 norm; an all-zero code stays zero.
std::vector<float> NormalizedCode(std::span<const float> code);

// Writes NormalizedCode(code) into `out` (of code's size) without
// allocating; the same values, bit for bit.
void NormalizeInto(std::span<const float> code, std::span<float> out);

// 1 / |code| (the norm in double precision), 0 for an all-zero code: the
// scale under which an index keeps a code as uploaded and searches its unit
// version (UnitScale(code) * code is NormalizedCode(code) up to float
// rounding).
float UnitScale(std::span<const float> code);

// |scale * vector|², summed in double precision.
double ScaledSquaredNorm(std::span<const float> vector, float scale);

// Feature-spatial code of `trace`: its normalised code followed by
// (x, y, z) / spatial_scale_m. Dimension = code size + 3.
Eigen::VectorXf FeatureSpatialCode(const MemoryTrace& trace,
                                   double spatial_scale_m);

// Euclidean distance between the normalised forms of two codes of equal
// size, in [0, 2]. This is the distance QueryPlace reports.
float CodeDistance(std::span<const float> a, std::span<const float> b);

}  // namespace fleetmem::core

#endif  // FLEETMEM_SERVICES_CORE_FEATURE_SPACE_H_
