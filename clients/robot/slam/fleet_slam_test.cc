#include "clients/robot/slam/fleet_slam.h"

#include "gtest/gtest.h"
#include "fleetmem_paths.h"

namespace fleetmem::slam {
namespace {

const std::string kAces =
    std::string(FLEETMEM_DATA_DIR) + "/laser/aces.clf.bz2";

absl::StatusOr<std::unique_ptr<KeyframeSource>> OpenAces() {
  absl::StatusOr<std::unique_ptr<robot::ObservationSource>> inner =
      robot::OpenSource("carmen:" + kAces);
  if (!inner.ok()) return inner.status();
  return KeyframeSource::Open(*std::move(inner), LaserSlamOptions{});
}

TEST(KeyframeSourceTest, ChoosesWhatLaserSlamChooses) {
  absl::StatusOr<std::unique_ptr<KeyframeSource>> source = OpenAces();
  ASSERT_TRUE(source.ok()) << source.status();
  const KeyframeSource& k = **source;
  ASSERT_GT(k.size(), 100u);
  EXPECT_LT(k.size(), k.inner().size() / 5);
  // LaserSlam deciding by motion on every scan makes the same keyframes.
  LaserSlam slam("r", {});
  std::vector<int64_t> chosen;
  for (size_t i = 0; i < k.inner().size(); ++i) {
    absl::StatusOr<robot::Observation> o = k.inner().Read(i);
    ASSERT_TRUE(o.ok());
    if (slam.AddScan(o->timestamp_ns, {o->place.x, o->place.y, o->place.yaw},
                     o->scan)) {
      chosen.push_back(o->timestamp_ns);
    }
  }
  ASSERT_EQ(chosen.size(), k.size());
  for (size_t i = 0; i < k.size(); ++i) {
    absl::StatusOr<robot::Observation> o = k.Read(i);
    ASSERT_TRUE(o.ok());
    EXPECT_EQ(o->index, i);
    EXPECT_EQ(o->timestamp_ns, chosen[i]) << i;
    if (i > 0) EXPECT_GT(k.inner_index(i), k.inner_index(i - 1));
  }
  EXPECT_EQ(k.Read(k.size()).status().code(), absl::StatusCode::kOutOfRange);
}

TEST(KeyframeSourceTest, RefusesASourceWithoutScans) {
  absl::StatusOr<std::unique_ptr<robot::ObservationSource>> images =
      robot::OpenSource(std::string("nordland:") + FLEETMEM_DATA_DIR +
                        "/nordland/summer");
  ASSERT_TRUE(images.ok()) << images.status();
  absl::StatusOr<std::unique_ptr<KeyframeSource>> k =
      KeyframeSource::Open(*std::move(images), LaserSlamOptions{});
  EXPECT_EQ(k.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(k.status().message().find("laser source"), std::string::npos);
}

}  // namespace
}  // namespace fleetmem::slam
