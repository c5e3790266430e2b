// TraceTable: the traces of a load waiting for the clusters that list them.
#include "services/storage/record_codec.h"

#include <optional>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "services/storage/keys.h"
#include "services/storage/testing/store_test_util.h"

namespace fleetmem::storage {
namespace {

core::MemoryTrace TraceOf(const std::string& robot, uint64_t seq,
                          uint64_t cluster_id) {
  core::MemoryTrace trace = testing::MakeTrace(robot, seq);
  trace.cluster_id = cluster_id;
  return trace;
}

TEST(TraceTableTest, EachTraceIsTakenOnceByItsOwnCluster) {
  TraceTable table;
  // Out of key order (an image's records need not be sorted).
  table.Add(TraceOf("r2", 1, 7));
  table.Add(TraceOf("r1", 10, 7));
  table.Add(TraceOf("r1", 2, 8));
  EXPECT_EQ(table.Take({"r1", 2}, 7), std::nullopt);  // another cluster's
  EXPECT_EQ(table.Take({"r1", 3}, 8), std::nullopt);  // absent
  std::optional<core::MemoryTrace> taken = table.Take({"r1", 2}, 8);
  ASSERT_TRUE(taken.has_value());
  EXPECT_EQ(taken->seq, 2u);
  EXPECT_EQ(taken->robot_id, "r1");
  EXPECT_FALSE(table.Take({"r1", 2}, 8));  // once
  ASSERT_TRUE(table.Take({"r2", 1}, 7));
  const core::MemoryTrace* left = table.AnyLeft();
  ASSERT_NE(left, nullptr);
  EXPECT_EQ(left->key(), (core::TraceKey{"r1", 10}));
  ASSERT_TRUE(table.Take({"r1", 10}, 7));
  EXPECT_EQ(table.AnyLeft(), nullptr);
}

TEST(TraceTableTest, AKeyAddedTwiceLeavesOneCopyOver) {
  TraceTable table;
  table.Add(TraceOf("r1", 1, 3));
  core::MemoryTrace second = TraceOf("r1", 1, 3);
  second.domain = "second";
  table.Add(second);
  std::optional<core::MemoryTrace> taken = table.Take({"r1", 1}, 3);
  ASSERT_TRUE(taken.has_value());
  EXPECT_NE(taken->domain, "second");  // the first added
  EXPECT_FALSE(table.Take({"r1", 1}, 3));
  ASSERT_NE(table.AnyLeft(), nullptr);
  EXPECT_EQ(table.AnyLeft()->domain, "second");
}

TEST(RecordCodecTest, ATraceDecodesWithoutItsCodeWhenAsked) {
  const core::MemoryTrace trace = TraceOf("r1", 5, 2);
  const std::string key = keys::TraceKey("f", trace.key());
  const std::string value = EncodeTrace(trace);
  absl::StatusOr<core::MemoryTrace> with = DecodeTrace(key, value);
  ASSERT_TRUE(with.ok()) << with.status();
  EXPECT_EQ(with->code, trace.code);
  core::TraceKey asked;
  absl::StatusOr<core::MemoryTrace> without =
      DecodeTrace(key, value, [&](const core::TraceKey& k) {
        asked = k;
        return false;
      });
  ASSERT_TRUE(without.ok()) << without.status();
  EXPECT_EQ(asked, trace.key());
  EXPECT_TRUE(without->code.empty());
  core::MemoryTrace expected = *with;
  expected.code.clear();
  EXPECT_EQ(testing::Dump(engine::FleetRecord{.pending = {*without}}),
            testing::Dump(engine::FleetRecord{.pending = {expected}}));
}

}  // namespace
}  // namespace fleetmem::storage
