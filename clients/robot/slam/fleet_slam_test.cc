#include "clients/robot/slam/fleet_slam.h"

#include <algorithm>
#include <memory>

#include "fleetmem_paths.h"
#include "gtest/gtest.h"

namespace fleetmem::slam {
namespace {

const std::string kAces =
    std::string(FLEETMEM_DATA_DIR) + "/laser/aces.clf.bz2";

// The first `limit` observations of a source. Choosing keyframes runs the
// scan matcher on every scan, twice in the test below: over all of ACES that
// took 137 s alone under AddressSanitizer and overran its 300 s beside other
// tests in CI, so the test reads the first 1,500 scans (22 s under ASan); the
// slow tier's fleetmem_fleet_slam_test runs KeyframeSource over the whole log.
class PrefixSource : public robot::ObservationSource {
 public:
  PrefixSource(std::unique_ptr<robot::ObservationSource> inner, size_t limit)
      : inner_(std::move(inner)), size_(std::min(limit, inner_->size())) {}

  const std::string& description() const override {
    return inner_->description();
  }
  size_t size() const override { return size_; }
  absl::StatusOr<robot::Observation> Read(size_t index) const override {
    if (index >= size_) return absl::OutOfRangeError("past the prefix");
    return inner_->Read(index);
  }
  std::string default_domain() const override {
    return inner_->default_domain();
  }
  std::string default_encoder() const override {
    return inner_->default_encoder();
  }
  double default_match_radius() const override {
    return inner_->default_match_radius();
  }
  bool places_are_ground_truth() const override {
    return inner_->places_are_ground_truth();
  }

 private:
  std::unique_ptr<robot::ObservationSource> inner_;
  size_t size_;
};

constexpr size_t kAcesPrefix = 1500;

absl::StatusOr<std::unique_ptr<KeyframeSource>> OpenAces() {
  absl::StatusOr<std::unique_ptr<robot::ObservationSource>> inner =
      robot::OpenSource("carmen:" + kAces);
  if (!inner.ok()) return inner.status();
  if ((*inner)->size() <= kAcesPrefix) {
    return absl::FailedPreconditionError("ACES holds fewer scans than assumed");
  }
  return KeyframeSource::Open(
      std::make_unique<PrefixSource>(*std::move(inner), kAcesPrefix),
      LaserSlamOptions{});
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
