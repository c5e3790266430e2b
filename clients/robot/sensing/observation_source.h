// Where a robot's observations come from, behind one small interface. Three
// sources read real recordings:
//
//   nordland:DIR          a Nordland-style folder of `images-NNNNN.png`
//                         (nordland.h): place x = NNNNN, y = z = 0 (route
//                         units, 10 between files; ground truth).
//   images:DIR,POSES.csv  a folder of images with a CSV of their poses
//                         (ground truth): a header line naming the columns
//                         `file`, `x`, `y` and optionally `z`, `yaw`,
//                         `timestamp_ns`, then one line per image, in the
//                         order the robot observes them.
//   carmen:FILE           2-D laser scans of a CARMEN log (carmen_log.h),
//                         `.clf` or bzip2-compressed `.clf.bz2`: every
//                         FLASER record, placed at its (odometry) pose.
//
// Sources are random-access, so that a restarted robot resumes at the
// index it had reached. Every error names the file (and line).
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_SOURCE_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_SOURCE_H_

#include <cstddef>
#include <memory>
#include <string>
#include <string_view>

#include "absl/status/statusor.h"
#include "clients/robot/sensing/observation.h"

namespace fleetmem::robot {

// Thread-compatible: Read is const and may run concurrently.
class ObservationSource {
 public:
  virtual ~ObservationSource() = default;

  // The spec it was opened from, e.g. "nordland:/data/nordland/summer".
  virtual const std::string& description() const = 0;
  // Observations in the source.
  virtual size_t size() const = 0;
  // Observation `index` (< size()). NOT_FOUND / DATA_LOSS naming the file
  // if it is missing or does not decode; OUT_OF_RANGE past the end.
  virtual absl::StatusOr<Observation> Read(size_t index) const = 0;

  // Defaults a robot uses unless told otherwise: the domain of its traces
  // ("summer" for .../summer, "images", "lidar"), the encoder, and the
  // distance within which a relocalisation counts as correct (place units:
  // 20 route units = +-2 files for Nordland, 2 m for poses and scans).
  virtual std::string default_domain() const = 0;
  virtual std::string default_encoder() const = 0;
  virtual double default_match_radius() const = 0;
  // Whether an observation's place is ground truth (Nordland's route
  // position, a pose file) or only odometry (a laser log's pose).
  virtual bool places_are_ground_truth() const = 0;
};

absl::StatusOr<std::unique_ptr<ObservationSource>> OpenNordlandFolder(
    const std::string& dir);
absl::StatusOr<std::unique_ptr<ObservationSource>> OpenImageFolder(
    const std::string& dir, const std::string& poses_csv);
absl::StatusOr<std::unique_ptr<ObservationSource>> OpenCarmenSource(
    const std::string& path);

// One of the specs above. INVALID_ARGUMENT for an unknown kind or a
// malformed spec; the errors of the source otherwise.
absl::StatusOr<std::unique_ptr<ObservationSource>> OpenSource(
    std::string_view spec);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_OBSERVATION_SOURCE_H_
