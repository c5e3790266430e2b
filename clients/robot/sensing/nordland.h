// The Nordland railway recordings under ../shared/data/nordland (README.md
// there): the same 2,500 places seen in summer and in winter, one 64x32 PNG
// per place, `images-NNNNN.png` with NNNNN = 10, 20, ..., 25000. The same
// file name is the same place; a frame's place along the route is its number
// (x = NNNNN, y = z = 0; 10 units between consecutive files).
#ifndef FLEETMEM_CLIENTS_ROBOT_SENSING_NORDLAND_H_
#define FLEETMEM_CLIENTS_ROBOT_SENSING_NORDLAND_H_

#include <cstddef>
#include <string>
#include <string_view>
#include <vector>

#include "absl/status/statusor.h"
#include "opencv2/core.hpp"

namespace fleetmem::robot {

// Distance along the route between consecutive files, in place units.
inline constexpr int kNordlandUnitsPerFile = 10;

// "images-01230.png" for 1230.
std::string NordlandFileName(int number);

// Numbers of the `images-NNNNN.png` files in `season_dir`, ascending.
// NOT_FOUND if the folder does not exist or holds no such file.
absl::StatusOr<std::vector<int>> ListNordlandFrames(
    const std::string& season_dir);

// Decodes an image file's bytes (PNG or JPEG, told by their signature) to an
// 8-bit single-channel image. DATA_LOSS naming `name` for any other format
// or bytes that do not decode. (The parser behind
// LoadNordlandGrey, fuzzed by image_decode_fuzz.cc.)
absl::StatusOr<cv::Mat> DecodeGrey(std::string_view bytes,
                                   const std::string& name);

// The image file `path` as an 8-bit single-channel image: ReadFile's errors,
// then DecodeGrey's.
absl::StatusOr<cv::Mat> LoadGrey(const std::string& path);

// The frame `number` of `season_dir` as an 8-bit single-channel image (the
// files hold grey content in three channels). Black frames (tunnels,
// stations) are returned as they are. NOT_FOUND if the file is missing,
// DATA_LOSS if it cannot be decoded.
absl::StatusOr<cv::Mat> LoadNordlandGrey(const std::string& season_dir,
                                         int number);

// Frames [begin, end) of a season's sorted frame list: one robot's drive.
struct Stretch {
  size_t begin = 0;
  size_t end = 0;
};

// `count` disjoint stretches of `length` consecutive frames spread evenly
// over `total` frames (stretch i starts at i * total / count), so robots
// cover different parts of the route. INVALID_ARGUMENT unless count >= 1,
// length >= 1 and count * length <= total.
absl::StatusOr<std::vector<Stretch>> SpreadStretches(size_t total, int count,
                                                     int length);

}  // namespace fleetmem::robot

#endif  // FLEETMEM_CLIENTS_ROBOT_SENSING_NORDLAND_H_
