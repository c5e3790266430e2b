#include "clients/robot/sensing/observation_source.h"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <map>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/string_view.h"
#include "clients/robot/sensing/carmen_log.h"
#include "clients/robot/sensing/image_encoder.h"
#include "clients/robot/sensing/nordland.h"
#include "clients/robot/sensing/scan_encoder.h"

namespace fleetmem::robot {
namespace {

absl::Status OutOfRange(const std::string& description, size_t index,
                        size_t size) {
  return absl::OutOfRangeError(absl::StrCat(
      description, " has ", size, " observations; there is no index ", index));
}

class NordlandSource : public ObservationSource {
 public:
  NordlandSource(std::string description, std::string dir,
                 std::vector<int> numbers)
      : description_(std::move(description)),
        dir_(std::move(dir)),
        numbers_(std::move(numbers)) {}

  const std::string& description() const override { return description_; }
  size_t size() const override { return numbers_.size(); }
  absl::StatusOr<Observation> Read(size_t index) const override {
    if (index >= numbers_.size()) {
      return OutOfRange(description_, index, numbers_.size());
    }
    absl::StatusOr<cv::Mat> grey = LoadNordlandGrey(dir_, numbers_[index]);
    if (!grey.ok()) return grey.status();
    Observation observation;
    observation.index = index;
    observation.name = NordlandFileName(numbers_[index]);
    observation.place.x = numbers_[index];
    observation.image = *std::move(grey);
    return observation;
  }
  std::string default_domain() const override {
    const std::string leaf =
        std::filesystem::path(dir_).lexically_normal().filename().string();
    return leaf.empty() ? "nordland" : leaf;
  }
  std::string default_encoder() const override {
    return ImageEncoderNames().front();
  }
  double default_match_radius() const override {
    return 2.0 * kNordlandUnitsPerFile;
  }
  bool places_are_ground_truth() const override { return true; }

 private:
  std::string description_;
  std::string dir_;
  std::vector<int> numbers_;
};

struct PosedImage {
  std::string file;
  core::Place place;
  int64_t timestamp_ns = 0;
};

class ImageFolderSource : public ObservationSource {
 public:
  ImageFolderSource(std::string description, std::string dir,
                    std::vector<PosedImage> images)
      : description_(std::move(description)),
        dir_(std::move(dir)),
        images_(std::move(images)) {}

  const std::string& description() const override { return description_; }
  size_t size() const override { return images_.size(); }
  absl::StatusOr<Observation> Read(size_t index) const override {
    if (index >= images_.size()) {
      return OutOfRange(description_, index, images_.size());
    }
    const PosedImage& entry = images_[index];
    absl::StatusOr<cv::Mat> grey =
        LoadGrey((std::filesystem::path(dir_) / entry.file).string());
    if (!grey.ok()) return grey.status();
    Observation observation;
    observation.index = index;
    observation.name = entry.file;
    observation.place = entry.place;
    observation.timestamp_ns = entry.timestamp_ns;
    observation.image = *std::move(grey);
    return observation;
  }
  std::string default_domain() const override { return "images"; }
  std::string default_encoder() const override {
    return ImageEncoderNames().front();
  }
  double default_match_radius() const override { return 2.0; }
  bool places_are_ground_truth() const override { return true; }

 private:
  std::string description_;
  std::string dir_;
  std::vector<PosedImage> images_;
};

class CarmenSource : public ObservationSource {
 public:
  CarmenSource(std::string description, std::vector<Observation> scans)
      : description_(std::move(description)), scans_(std::move(scans)) {}

  const std::string& description() const override { return description_; }
  size_t size() const override { return scans_.size(); }
  absl::StatusOr<Observation> Read(size_t index) const override {
    if (index >= scans_.size()) {
      return OutOfRange(description_, index, scans_.size());
    }
    return scans_[index];
  }
  std::string default_domain() const override { return "lidar"; }
  std::string default_encoder() const override {
    return ScanEncoderNames().front();
  }
  double default_match_radius() const override { return 2.0; }
  bool places_are_ground_truth() const override { return false; }

 private:
  std::string description_;
  std::vector<Observation> scans_;
};

// Parses the poses CSV (see the header comment) of an image folder.
absl::StatusOr<std::vector<PosedImage>> ParsePosesCsv(const std::string& path) {
  std::ifstream in(path);
  if (!in) return absl::NotFoundError(absl::StrCat("cannot open ", path));
  std::map<std::string, size_t> column;
  std::vector<PosedImage> images;
  std::string line;
  size_t line_number = 0;
  auto error = [&](std::string_view what) {
    return absl::InvalidArgumentError(
        absl::StrCat(path, ":", line_number, ": ", std::string(what)));
  };
  while (std::getline(in, line)) {
    ++line_number;
    const absl::string_view text = absl::StripAsciiWhitespace(line);
    if (text.empty() || text[0] == '#') continue;
    std::vector<std::string> fields;
    for (absl::string_view field : absl::StrSplit(text, ',')) {
      fields.emplace_back(absl::StripAsciiWhitespace(field));
    }
    if (column.empty()) {
      for (size_t i = 0; i < fields.size(); ++i) column[fields[i]] = i;
      for (const char* required : {"file", "x", "y"}) {
        if (!column.contains(required)) {
          return error(absl::StrCat(
              "the header line must name the columns file, x, y (and may "
              "name z, yaw, timestamp_ns); \"",
              required, "\" is missing"));
        }
      }
      continue;
    }
    if (fields.size() != column.size()) {
      return error(absl::StrCat("expected ", column.size(), " fields, got ",
                                fields.size()));
    }
    PosedImage image;
    image.file = fields[column["file"]];
    if (image.file.empty()) return error("empty file name");
    const std::pair<const char*, double*> numbers[] = {
        {"x", &image.place.x},
        {"y", &image.place.y},
        {"z", &image.place.z},
        {"yaw", &image.place.yaw}};
    for (const auto& [name, value] : numbers) {
      auto it = column.find(name);
      if (it == column.end()) continue;
      if (!absl::SimpleAtod(fields[it->second], value) ||
          !std::isfinite(*value)) {
        return error(absl::StrCat(name, " \"", fields[it->second],
                                  "\" is not a finite number"));
      }
    }
    if (auto it = column.find("timestamp_ns");
        it != column.end() &&
        !absl::SimpleAtoi(fields[it->second], &image.timestamp_ns)) {
      return error(absl::StrCat("timestamp_ns \"", fields[it->second],
                                "\" is not an integer"));
    }
    images.push_back(std::move(image));
  }
  if (in.bad()) return absl::DataLossError(absl::StrCat("cannot read ", path));
  if (images.empty()) {
    return absl::NotFoundError(absl::StrCat(path, " lists no image"));
  }
  return images;
}

}  // namespace

absl::StatusOr<std::unique_ptr<ObservationSource>> OpenNordlandFolder(
    const std::string& dir) {
  absl::StatusOr<std::vector<int>> numbers = ListNordlandFrames(dir);
  if (!numbers.ok()) return numbers.status();
  return std::make_unique<NordlandSource>(absl::StrCat("nordland:", dir), dir,
                                          *std::move(numbers));
}

absl::StatusOr<std::unique_ptr<ObservationSource>> OpenImageFolder(
    const std::string& dir, const std::string& poses_csv) {
  if (!std::filesystem::is_directory(dir)) {
    return absl::NotFoundError(absl::StrCat("no image folder ", dir));
  }
  absl::StatusOr<std::vector<PosedImage>> images = ParsePosesCsv(poses_csv);
  if (!images.ok()) return images.status();
  return std::make_unique<ImageFolderSource>(
      absl::StrCat("images:", dir, ",", poses_csv), dir, *std::move(images));
}

absl::StatusOr<std::unique_ptr<ObservationSource>> OpenCarmenSource(
    const std::string& path) {
  absl::StatusOr<std::string> text = ReadMaybeBzip2(path);
  if (!text.ok()) return text.status();
  const std::string name = std::filesystem::path(path).filename().string();
  absl::StatusOr<std::vector<Observation>> scans = ParseCarmenLog(*text, name);
  if (!scans.ok()) return scans.status();
  return std::make_unique<CarmenSource>(absl::StrCat("carmen:", path),
                                        *std::move(scans));
}

absl::StatusOr<std::unique_ptr<ObservationSource>> OpenSource(
    std::string_view spec) {
  const size_t colon = spec.find(':');
  const std::string_view kind = spec.substr(0, colon);
  const std::string rest(colon == std::string_view::npos
                             ? std::string_view()
                             : spec.substr(colon + 1));
  if (colon == std::string_view::npos || rest.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "source \"", std::string(spec),
        "\" must be nordland:DIR, images:DIR,POSES.csv or carmen:FILE"));
  }
  if (kind == "nordland") return OpenNordlandFolder(rest);
  if (kind == "carmen") return OpenCarmenSource(rest);
  if (kind == "images") {
    const size_t comma = rest.rfind(',');
    if (comma == std::string::npos || comma == 0 || comma + 1 == rest.size()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "source \"", std::string(spec), "\" must be images:DIR,POSES.csv"));
    }
    return OpenImageFolder(rest.substr(0, comma), rest.substr(comma + 1));
  }
  return absl::InvalidArgumentError(absl::StrCat(
      "unknown source kind \"", std::string(kind),
      "\"; use nordland:DIR, images:DIR,POSES.csv or carmen:FILE"));
}

}  // namespace fleetmem::robot
