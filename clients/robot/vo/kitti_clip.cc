#include "clients/robot/vo/kitti_clip.h"

#include <algorithm>
#include <filesystem>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "services/common/files.h"
#include "opencv2/imgcodecs.hpp"
#include "opencv2/imgproc.hpp"

namespace fleetmem::vo {
namespace {

namespace fs = std::filesystem;

absl::StatusOr<std::vector<double>> Numbers(std::string_view line,
                                            const std::string& name,
                                            int line_number) {
  std::vector<double> values;
  for (absl::string_view field :
       absl::StrSplit(absl::string_view(line.data(), line.size()), ' ',
                      absl::SkipWhitespace())) {
    if (field.back() == ':') continue;  // "P0:"
    double v = 0.0;
    if (!absl::SimpleAtod(field, &v) || !std::isfinite(v)) {
      return absl::InvalidArgumentError(absl::StrCat(
          name, ":", line_number, ": '", field, "' is not a number"));
    }
    values.push_back(v);
  }
  if (values.size() != 12) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ":", line_number,
                     ": a projection matrix needs 12 "
                     "numbers, found ",
                     values.size()));
  }
  return values;
}

// The PNGs of `dir` in name order, resized to width x height when both are
// > 0; `original` (if given) gets the first image's size before resizing.
absl::StatusOr<std::vector<cv::Mat>> ReadImages(const fs::path& dir, int width,
                                                int height,
                                                cv::Size* original = nullptr) {
  std::vector<fs::path> files;
  std::error_code ec;
  for (const fs::directory_entry& e : fs::directory_iterator(dir, ec)) {
    if (e.path().extension() == ".png") files.push_back(e.path());
  }
  if (ec) {
    return absl::NotFoundError(
        absl::StrCat("cannot list ", dir.string(), ": ", ec.message()));
  }
  std::sort(files.begin(), files.end());
  std::vector<cv::Mat> images;
  for (const fs::path& f : files) {
    cv::Mat image = cv::imread(f.string(), cv::IMREAD_GRAYSCALE);
    if (image.empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat(f.string(), " is not a readable image"));
    }
    if (original != nullptr && images.empty()) *original = image.size();
    if (width > 0 && height > 0) {
      cv::Mat sized;
      cv::resize(image, sized, cv::Size(width, height), 0, 0, cv::INTER_AREA);
      image = sized;
    }
    images.push_back(image);
  }
  return images;
}

}  // namespace

absl::StatusOr<Camera> ParseKittiCalibration(std::string_view text,
                                             const std::string& name) {
  std::vector<slam::DataLine> lines = slam::DataLines(text);
  if (lines.empty()) {
    return absl::InvalidArgumentError(name + ": no projection matrix");
  }
  absl::StatusOr<std::vector<double>> p0 =
      Numbers(lines[0].text, name, lines[0].number);
  if (!p0.ok()) return p0.status();
  Camera camera;
  camera.fx = (*p0)[0];
  camera.cx = (*p0)[2];
  camera.fy = (*p0)[5];
  camera.cy = (*p0)[6];
  if (!(camera.fx > 0.0) || !(camera.fy > 0.0)) {
    return absl::InvalidArgumentError(
        absl::StrCat(name, ": P0's focal lengths must be positive"));
  }
  if (lines.size() > 1) {
    absl::StatusOr<std::vector<double>> p1 =
        Numbers(lines[1].text, name, lines[1].number);
    if (!p1.ok()) return p1.status();
    camera.baseline_m = -(*p1)[3] / (*p1)[0];
  }
  return camera;
}

absl::StatusOr<KittiClip> LoadKittiClip(const std::string& dir, int width,
                                        int height) {
  const fs::path root(dir);
  if (!fs::is_directory(root)) {
    return absl::NotFoundError(absl::StrCat("no clip folder ", dir));
  }
  KittiClip clip;
  clip.name = root.filename().string();
  if (clip.name.empty()) clip.name = root.parent_path().filename().string();
  absl::StatusOr<std::string> calib =
      files::ReadFile((root / "calib.txt").string());
  if (!calib.ok()) return calib.status();
  absl::StatusOr<Camera> camera =
      ParseKittiCalibration(*calib, (root / "calib.txt").string());
  if (!camera.ok()) return camera.status();
  cv::Size original;
  absl::StatusOr<std::vector<cv::Mat>> left =
      ReadImages(root / "image_l", width, height, &original);
  if (!left.ok()) return left.status();
  if (left->empty()) {
    return absl::NotFoundError(absl::StrCat("no frames in ", dir, "/image_l"));
  }
  camera->width = original.width;
  camera->height = original.height;
  clip.camera =
      width > 0 && height > 0 ? ResizedCamera(*camera, width, height) : *camera;
  clip.left = std::move(*left);
  if (fs::is_directory(root / "image_r")) {
    absl::StatusOr<std::vector<cv::Mat>> right =
        ReadImages(root / "image_r", width, height);
    if (!right.ok()) return right.status();
    if (right->size() != clip.left.size()) {
      return absl::InvalidArgumentError(
          absl::StrCat(dir, ": ", right->size(), " right frames for ",
                       clip.left.size(), " left frames"));
    }
    clip.right = std::move(*right);
  }
  absl::StatusOr<slam::Trajectory> poses = slam::ReadTrajectoryFile(
      (root / "poses.txt").string(), slam::TrajectoryFormat::kKitti);
  if (!poses.ok()) return poses.status();
  if (poses->size() != clip.left.size()) {
    return absl::InvalidArgumentError(absl::StrCat(
        dir, ": ", poses->size(), " poses for ", clip.left.size(), " frames"));
  }
  clip.travelled_m.assign(poses->size(), 0.0);
  for (size_t i = 0; i < poses->size(); ++i) {
    (*poses)[i].time_s = i * clip.frame_interval_s;
    if (i > 0) {
      clip.travelled_m[i] =
          ((*poses)[i].pose.translation() - (*poses)[i - 1].pose.translation())
              .norm();
    }
  }
  clip.ground_truth = std::move(*poses);
  return clip;
}

KittiClip SubClip(const KittiClip& clip, size_t first, size_t count) {
  KittiClip sub;
  sub.name = clip.name;
  sub.camera = clip.camera;
  sub.frame_interval_s = clip.frame_interval_s;
  const size_t end = std::min(clip.left.size(), first + count);
  const Eigen::Isometry3d origin = first < end
                                       ? clip.ground_truth[first].pose.inverse()
                                       : Eigen::Isometry3d::Identity();
  for (size_t i = first; i < end; ++i) {
    sub.left.push_back(clip.left[i]);
    if (!clip.right.empty()) sub.right.push_back(clip.right[i]);
    slam::StampedPose p = clip.ground_truth[i];
    p.pose = origin * p.pose;
    p.time_s = (i - first) * clip.frame_interval_s;
    sub.ground_truth.push_back(p);
    sub.travelled_m.push_back(i == first ? 0.0 : clip.travelled_m[i]);
  }
  return sub;
}

}  // namespace fleetmem::vo
