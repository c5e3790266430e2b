#include "clients/robot/sensing/observation_source.h"

#include <unistd.h>

#include <filesystem>
#include <fstream>

#include "absl/strings/str_cat.h"
#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "opencv2/imgcodecs.hpp"
#include "services/common/files.h"

namespace fleetmem::robot {
namespace {

using ::testing::HasSubstr;

const std::string kData = FLEETMEM_DATA_DIR;

// Image folders the tests make (the project's one temporary-directory
// helper).
class TempFolder : public files::TempDir {
 public:
  TempFolder() : files::TempDir("fleetmem-source-") {}
};

TEST(ObservationSourceTest, NordlandFolderPlacesFramesByNumber) {
  absl::StatusOr<std::unique_ptr<ObservationSource>> source =
      OpenSource("nordland:" + kData + "/nordland/winter");
  ASSERT_TRUE(source.ok()) << source.status();
  EXPECT_EQ((*source)->size(), 2500u);
  EXPECT_EQ((*source)->default_domain(), "winter");
  EXPECT_DOUBLE_EQ((*source)->default_match_radius(), 20.0);
  EXPECT_TRUE((*source)->places_are_ground_truth());
  absl::StatusOr<Observation> frame = (*source)->Read(122);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(frame->name, "images-01230.png");
  EXPECT_DOUBLE_EQ(frame->place.x, 1230.0);
  EXPECT_EQ(frame->image.type(), CV_8UC1);
  EXPECT_EQ(frame->image.cols, 64);
  EXPECT_EQ((*source)->Read(2500).status().code(),
            absl::StatusCode::kOutOfRange);
}

TEST(ObservationSourceTest, CarmenSourceReadsTheRealLog) {
  absl::StatusOr<std::unique_ptr<ObservationSource>> source =
      OpenSource("carmen:" + kData + "/laser/aces.clf.bz2");
  ASSERT_TRUE(source.ok()) << source.status();
  EXPECT_EQ((*source)->size(), 7374u);
  EXPECT_EQ((*source)->default_domain(), "lidar");
  EXPECT_EQ((*source)->default_encoder(), "scanring-r32-d32");
  EXPECT_FALSE((*source)->places_are_ground_truth());  // odometry
  absl::StatusOr<Observation> scan = (*source)->Read(7373);
  ASSERT_TRUE(scan.ok());
  EXPECT_EQ(scan->scan.ranges.size(), 180u);
}

TEST(ObservationSourceTest, ImageFolderWithPosesCsv) {
  TempFolder folder;
  cv::Mat image(20, 40, CV_8UC1, cv::Scalar(90));
  ASSERT_TRUE(cv::imwrite(folder.Join("a.png"), image));
  ASSERT_TRUE(cv::imwrite(folder.Join("b.png"), image));
  std::ofstream(folder.Join("poses.csv"))
      << "file,x,y,yaw\n# comment\na.png,1.5,2,0.1\n\nb.png,3,4,0\n";
  absl::StatusOr<std::unique_ptr<ObservationSource>> source = OpenSource(
      absl::StrCat("images:", folder.path(), ",", folder.Join("poses.csv")));
  ASSERT_TRUE(source.ok()) << source.status();
  ASSERT_EQ((*source)->size(), 2u);
  absl::StatusOr<Observation> b = (*source)->Read(1);
  ASSERT_TRUE(b.ok()) << b.status();
  EXPECT_EQ(b->name, "b.png");
  EXPECT_DOUBLE_EQ(b->place.x, 3.0);
  EXPECT_DOUBLE_EQ(b->place.y, 4.0);
}

TEST(ObservationSourceTest, BadInputNamesTheFileAndLine) {
  TempFolder folder;
  std::ofstream(folder.Join("poses.csv")) << "file,x,y\na.png,1,2\nb.png,x,2\n";
  absl::StatusOr<std::unique_ptr<ObservationSource>> source = OpenSource(
      absl::StrCat("images:", folder.path(), ",", folder.Join("poses.csv")));
  ASSERT_EQ(source.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(source.status().message(),
              HasSubstr(folder.Join("poses.csv") + ":3: x \"x\""));

  std::ofstream(folder.Join("short.csv")) << "file,y\na.png,1\n";
  source = OpenSource(
      absl::StrCat("images:", folder.path(), ",", folder.Join("short.csv")));
  EXPECT_THAT(source.status().message(), HasSubstr("\"x\" is missing"));

  // A corrupt PNG is found when it is read, naming the file.
  std::ofstream(folder.Join("c.png")) << "\x89PNG\r\n\x1a\nnot really";
  std::ofstream(folder.Join("ok.csv")) << "file,x,y\nc.png,1,2\n";
  source = OpenSource(
      absl::StrCat("images:", folder.path(), ",", folder.Join("ok.csv")));
  ASSERT_TRUE(source.ok()) << source.status();
  absl::StatusOr<Observation> c = (*source)->Read(0);
  EXPECT_EQ(c.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_THAT(c.status().message(), HasSubstr(folder.Join("c.png")));

  EXPECT_EQ(OpenSource("nordland:/nonexistent").status().code(),
            absl::StatusCode::kNotFound);
  EXPECT_EQ(OpenSource("lidar:/x").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(OpenSource("images:/x").status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(OpenSource("nordland").status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace fleetmem::robot
