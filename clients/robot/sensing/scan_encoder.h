// A classical, rotation-invariant place code for 2-D laser scans: what a
// scan looks like does not depend on which way the robot faces, so the code
// is built only from quantities a rotation about the vertical axis leaves
// unchanged:
//
//   - a ring histogram: the share of beams whose range falls in each of
//     `range_bins` rings of equal width out to `histogram_range_m` (farther
//     returns fall in the last ring), plus the share of beams with no return;
//   - a shape distribution (D2, Osada et al. 2002): the histogram of the
//     distances between all pairs of scan points in `distance_bins` bins of
//     equal width out to `histogram_range_m`.
//
// Both halves are shares (they sum to 1 each), so scans with different beam
// counts compare.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_SCAN_ENCODER_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_SCAN_ENCODER_H_

#include <memory>

#include "clients/robot/sensing/encoder.h"

namespace fleetmem::robot {

struct ScanRingOptions {
  // Rings of the range histogram (plus one no-return bin).
  int range_bins = 32;
  // Bins of the pairwise-distance histogram.
  int distance_bins = 32;
  // Both histograms cover [0, histogram_range_m) metres; beyond goes to the
  // last bin.
  double histogram_range_m = 20.0;
  // Perturb (the internal reward's A): rotate the scan by a uniformly random
  // whole number of beams in [-max_rotation_beams, max_rotation_beams]; the
  // beams that rotate out of the field of view become no-return.
  int max_rotation_beams = 10;
};

// nullptr if the options are out of range (bins < 1, range <= 0, rotation
// < 0). dimension = range_bins + 1 + distance_bins.
std::unique_ptr<Encoder> NewScanRingEncoder(const ScanRingOptions& options);

// Names accepted by NewScanEncoderByName, the default first.
std::vector<std::string> ScanEncoderNames();
absl::StatusOr<std::unique_ptr<Encoder>> NewScanEncoderByName(
    std::string_view name);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_SCAN_ENCODER_H_
