#include "clients/robot/sensing/carmen_log.h"

#include <bzlib.h>

#include <cmath>
#include <cstdio>
#include <memory>

#include "absl/status/status.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "services/common/files.h"

namespace fleetmem::robot {
namespace {

constexpr int kMaxBeams = 4096;
// After the ranges: x y theta odom_x odom_y odom_theta ipc_timestamp.
constexpr int kFieldsAfterRanges = 7;

absl::Status LineError(const std::string& name, size_t line,
                       std::string_view what) {
  return absl::InvalidArgumentError(
      absl::StrCat(name, ":", line, ": ", std::string(what)));
}

}  // namespace

absl::StatusOr<std::vector<Observation>> ParseCarmenLog(
    std::string_view text, const std::string& name) {
  std::vector<Observation> scans;
  size_t line_number = 0;
  for (absl::string_view line :
       absl::StrSplit(absl::string_view(text.data(), text.size()), '\n')) {
    ++line_number;
    if (!absl::StartsWith(line, "FLASER")) continue;
    const std::vector<absl::string_view> fields =
        absl::StrSplit(line, absl::ByAnyChar(" \t\r"), absl::SkipEmpty());
    if (fields.size() < 2 || fields[0] != "FLASER") continue;
    int beams = 0;
    if (!absl::SimpleAtoi(fields[1], &beams) || beams < 1 ||
        beams > kMaxBeams) {
      return LineError(name, line_number,
                       absl::StrCat("FLASER beam count \"", fields[1],
                                    "\" is not in 1..", kMaxBeams));
    }
    const size_t needed = 2 + beams + kFieldsAfterRanges;
    if (fields.size() < needed) {
      return LineError(
          name, line_number,
          absl::StrCat("FLASER with ", beams, " beams needs ", needed,
                       " fields, got ", fields.size(), " (line cut short?)"));
    }
    Observation scan;
    scan.index = scans.size();
    scan.name = absl::StrCat(name, ":", line_number);
    scan.scan.ranges.resize(beams);
    for (int i = 0; i < beams; ++i) {
      float range = 0.0f;
      if (!absl::SimpleAtof(fields[2 + i], &range) || !std::isfinite(range) ||
          range < 0.0f) {
        return LineError(name, line_number,
                         absl::StrCat("range ", i + 1, " \"", fields[2 + i],
                                      "\" is not a finite number >= 0"));
      }
      scan.scan.ranges[i] = range;
    }
    double pose[4];  // x y theta, then ipc_timestamp
    const size_t at[4] = {2u + beams, 3u + beams, 4u + beams, 8u + beams};
    const char* what[4] = {"x", "y", "theta", "ipc_timestamp"};
    for (int k = 0; k < 4; ++k) {
      if (!absl::SimpleAtod(fields[at[k]], &pose[k]) ||
          !std::isfinite(pose[k])) {
        return LineError(name, line_number,
                         absl::StrCat(what[k], " \"", fields[at[k]],
                                      "\" is not a finite number"));
      }
    }
    scan.place =
        core::Place{.x = pose[0], .y = pose[1], .z = 0.0, .yaw = pose[2]};
    scan.timestamp_ns = static_cast<int64_t>(std::llround(pose[3] * 1e9));
    scans.push_back(std::move(scan));
  }
  if (scans.empty()) {
    return absl::NotFoundError(absl::StrCat(name, " holds no FLASER record"));
  }
  return scans;
}

absl::StatusOr<std::string> ReadMaybeBzip2(const std::string& path) {
  if (!absl::EndsWith(path, ".bz2")) return files::ReadFile(path);
  std::unique_ptr<FILE, int (*)(FILE*)> file(std::fopen(path.c_str(), "rb"),
                                             &std::fclose);
  if (file == nullptr) {
    return absl::NotFoundError(absl::StrCat("cannot open ", path));
  }
  int error = BZ_OK;
  BZFILE* bz = BZ2_bzReadOpen(&error, file.get(), 0, 0, nullptr, 0);
  if (bz == nullptr || error != BZ_OK) {
    return absl::DataLossError(
        absl::StrCat("cannot read ", path, " as bzip2 (error ", error, ")"));
  }
  std::string text;
  char buffer[1 << 16];
  while (true) {
    const int n = BZ2_bzRead(&error, bz, buffer, sizeof(buffer));
    if (error == BZ_OK || error == BZ_STREAM_END) text.append(buffer, n);
    if (error == BZ_STREAM_END) break;
    if (error != BZ_OK) {
      BZ2_bzReadClose(&error, bz);
      return absl::DataLossError(
          absl::StrCat(path, ": corrupt or truncated bzip2 data after ",
                       text.size(), " decompressed bytes"));
    }
  }
  BZ2_bzReadClose(&error, bz);
  return text;
}

}  // namespace fleetmem::robot
