#include "clients/robot/sensing/nordland.h"

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <system_error>

#include "absl/status/status.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/strip.h"
#include "opencv2/imgcodecs.hpp"
#include "services/common/files.h"

namespace fleetmem::robot {

std::string NordlandFileName(int number) {
  return absl::StrFormat("images-%05d.png", number);
}

absl::StatusOr<std::vector<int>> ListNordlandFrames(
    const std::string& season_dir) {
  std::error_code error;
  std::filesystem::directory_iterator it(season_dir, error);
  if (error) {
    return absl::NotFoundError(
        absl::StrCat("cannot list ", season_dir, ": ", error.message()));
  }
  std::vector<int> numbers;
  for (const auto& entry : it) {
    const std::string file_name = entry.path().filename().string();
    absl::string_view name = file_name;
    int number = 0;
    if (absl::ConsumePrefix(&name, "images-") &&
        absl::ConsumeSuffix(&name, ".png") && absl::SimpleAtoi(name, &number)) {
      numbers.push_back(number);
    }
  }
  if (numbers.empty()) {
    return absl::NotFoundError(
        absl::StrCat("no images-NNNNN.png files in ", season_dir));
  }
  std::sort(numbers.begin(), numbers.end());
  return numbers;
}

absl::StatusOr<cv::Mat> LoadNordlandGrey(const std::string& season_dir,
                                         int number) {
  const std::string path =
      (std::filesystem::path(season_dir) / NordlandFileName(number)).string();
  if (!std::filesystem::exists(path)) {
    return absl::NotFoundError(absl::StrCat("missing frame ", path));
  }
  return LoadGrey(path);
}

absl::StatusOr<cv::Mat> LoadGrey(const std::string& path) {
  absl::StatusOr<std::string> bytes = files::ReadFile(path);
  if (!bytes.ok()) return bytes.status();
  return DecodeGrey(*bytes, path);
}

absl::StatusOr<cv::Mat> DecodeGrey(std::string_view bytes,
                                   const std::string& name) {
  // Only PNG and JPEG reach OpenCV: imdecode would hand other bytes to every
  // decoder it has, and Debian's DICOM one (GDCM) aborts the process on
  // malformed input (found by image_decode_fuzz).
  constexpr std::string_view kPng("\x89PNG\r\n\x1a\n", 8);
  constexpr std::string_view kJpeg("\xff\xd8\xff", 3);
  if (!bytes.starts_with(kPng) && !bytes.starts_with(kJpeg)) {
    return absl::DataLossError(
        absl::StrCat("cannot decode ", name, ": not a PNG or JPEG file"));
  }
  cv::Mat grey;
  try {
    const cv::Mat raw(1, static_cast<int>(bytes.size()), CV_8UC1,
                      const_cast<char*>(bytes.data()));
    grey = cv::imdecode(raw, cv::IMREAD_GRAYSCALE);
  } catch (const cv::Exception& e) {
    return absl::DataLossError(
        absl::StrCat("cannot decode ", name, ": ", e.what()));
  }
  if (grey.empty()) {
    return absl::DataLossError(absl::StrCat("cannot decode ", name));
  }
  return grey;
}

absl::StatusOr<std::vector<Stretch>> SpreadStretches(size_t total, int count,
                                                     int length) {
  if (count < 1 || length < 1 ||
      static_cast<size_t>(count) * static_cast<size_t>(length) > total) {
    return absl::InvalidArgumentError(
        absl::StrCat(count, " stretches of ", length, " frames do not fit in ",
                     total, " frames"));
  }
  std::vector<Stretch> stretches;
  for (int i = 0; i < count; ++i) {
    const size_t begin = static_cast<size_t>(i) * total / count;
    stretches.push_back({begin, begin + static_cast<size_t>(length)});
  }
  return stretches;
}

}  // namespace fleetmem::robot
