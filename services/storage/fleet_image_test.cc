#include "services/storage/fleet_image.h"

#include <fstream>
#include <iterator>
#include <memory>
#include <string>
#include <vector>

#include "fleetmem_paths.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/storage/in_memory_store.h"
#include "services/storage/testing/store_test_util.h"

namespace fleetmem::storage {
namespace {

using ::testing::HasSubstr;

// A fleet's state after the scripted workload (every kind of record).
engine::FleetImage ScriptedImage() {
  std::unique_ptr<engine::MemoryStore> store = NewInMemoryStore();
  for (const engine::FleetMutation& mutation : testing::ScriptedMutations(40)) {
    EXPECT_TRUE(store->Apply("f1", mutation).ok());
  }
  engine::FleetImage image;
  absl::StatusOr<engine::FleetRecord> record = store->LoadFleet("f1");
  EXPECT_TRUE(record.ok()) << record.status();
  if (record.ok()) image.record = *std::move(record);
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      store->ReadEvents("f1", 0, 100000);
  EXPECT_TRUE(events.ok()) << events.status();
  if (events.ok()) image.events = *std::move(events);
  return image;
}

TEST(FleetImageTest, EveryRecordComesBackExactly) {
  const engine::FleetImage image = ScriptedImage();
  ASSERT_FALSE(image.record.clusters.empty());
  ASSERT_FALSE(image.record.pending.empty());
  ASSERT_FALSE(image.record.robots.empty());
  ASSERT_FALSE(image.events.empty());
  absl::StatusOr<std::string> bytes = EncodeFleetImage(image);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  absl::StatusOr<engine::FleetImage> decoded = DecodeFleetImage("f1", *bytes);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_EQ(testing::Dump(decoded->record), testing::Dump(image.record));
  EXPECT_EQ(testing::Dump(decoded->events), testing::Dump(image.events));
}

TEST(FleetImageTest, DamagedOrForeignImagesAreRefused) {
  engine::FleetImage image = ScriptedImage();
  absl::StatusOr<std::string> bytes = EncodeFleetImage(image);
  ASSERT_TRUE(bytes.ok()) << bytes.status();

  absl::StatusOr<engine::FleetImage> other = DecodeFleetImage("f2", *bytes);
  EXPECT_TRUE(absl::IsDataLoss(other.status())) << other.status();
  EXPECT_THAT(other.status().message(), HasSubstr("holds fleet \"f1\""));

  const std::string cut = bytes->substr(0, bytes->size() / 2);
  EXPECT_TRUE(absl::IsDataLoss(DecodeFleetImage("f1", cut).status()));
  EXPECT_TRUE(absl::IsDataLoss(DecodeFleetImage("f1", "").status()));

  // A cluster that lists a trace of another cluster.
  core::Cluster& first = image.record.clusters.front();
  core::MemoryTrace stray = first.traces.front();
  stray.seq += 1000000;
  first.traces.push_back(stray);
  first.traces.back().cluster_id = first.id + 1000;  // claims another cluster
  bytes = EncodeFleetImage(image);
  ASSERT_TRUE(bytes.ok());
  absl::StatusOr<engine::FleetImage> damaged = DecodeFleetImage("f1", *bytes);
  EXPECT_TRUE(absl::IsDataLoss(damaged.status())) << damaged.status();
  EXPECT_THAT(damaged.status().message(), HasSubstr("has no trace"));

  // A clustered trace without its code: a store would keep the one it
  // holds, so an image that lacks one is refused.
  image = ScriptedImage();
  image.record.clusters.back().traces.back().code.clear();
  bytes = EncodeFleetImage(image);
  ASSERT_TRUE(bytes.ok());
  damaged = DecodeFleetImage("f1", *bytes);
  EXPECT_TRUE(absl::IsDataLoss(damaged.status())) << damaged.status();
  EXPECT_THAT(damaged.status().message(), HasSubstr("has no code"));
}

// The fuzzer's seed (fuzz_corpus/fleet_image_fuzz) is a valid image, so
// the fuzzer starts past the parser's first checks.
TEST(FleetImageTest, TheFuzzSeedDecodes) {
  std::ifstream in(std::string(FLEETMEM_SOURCE_DIR) +
                       "/services/storage/fuzz_corpus/fleet_image_fuzz/"
                       "meta_and_pending.bin",
                   std::ios::binary);
  ASSERT_TRUE(in.good());
  const std::string bytes((std::istreambuf_iterator<char>(in)),
                          std::istreambuf_iterator<char>());
  absl::StatusOr<engine::FleetImage> image = DecodeFleetImage("f1", bytes);
  ASSERT_TRUE(image.ok()) << image.status();
  EXPECT_EQ(image->record.meta.code_dimension, 8u);
  ASSERT_EQ(image->record.pending.size(), 1u);
  EXPECT_EQ(image->record.pending[0].code.size(), 8u);
}

}  // namespace
}  // namespace fleetmem::storage
