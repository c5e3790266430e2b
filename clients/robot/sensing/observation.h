// One observation of a robot's sensor: an image or a 2-D laser scan, with
// where it was made and where it came from.
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_H_

#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "opencv2/core.hpp"
#include "services/core/types.h"

namespace fleetmem::robot {

// A planar laser scan: `ranges` (metres) at bearings spread evenly over
// `field_of_view` radians, counter-clockwise from -field_of_view / 2 (the
// CARMEN FLASER convention). A range <= 0 or >= max_range is no return.
struct LaserScan {
  std::vector<float> ranges;
  double field_of_view = 3.14159265358979323846;
  float max_range = 50.0f;
};

struct Observation {
  // Position in its source, from 0: what a restarted robot resumes from.
  size_t index = 0;
  // Where it came from, for messages: "images-01230.png", "aces.clf:812".
  std::string name;
  // Where it was made, in the fleet's map frame (see the source for what the
  // units are and whether this is ground truth or odometry).
  core::Place place;
  // Unix time of the recording in nanoseconds; 0 if the source has none.
  int64_t timestamp_ns = 0;
  // An 8-bit single-channel image; empty for a scan.
  cv::Mat image;
  // A scan; empty ranges for an image.
  LaserScan scan;
};

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_H_
