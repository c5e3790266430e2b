// TraceTable: the traces of a load waiting for the clusters that list them.
#include "services/storage/record_codec.h"

#include <algorithm>
#include <bit>
#include <cstdint>
#include <optional>
#include <random>
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

TEST(TraceTableTest, ForEachVisitsWhatIsLeftInKeyOrder) {
  TraceTable table;
  table.Add(TraceOf("r2", 1, 7));
  table.Add(TraceOf("r1", 10, 7));
  table.Add(TraceOf("r1", 2, 7));
  ASSERT_TRUE(table.Take({"r1", 10}, 7));
  std::vector<core::TraceKey> seen;
  ASSERT_TRUE(table
                  .ForEach([&](core::MemoryTrace& trace) {
                    seen.push_back(trace.key());
                    return absl::OkStatus();
                  })
                  .ok());
  EXPECT_EQ(seen, (std::vector<core::TraceKey>{{"r1", 2}, {"r2", 1}}));
  const absl::Status stopped = table.ForEach(
      [](core::MemoryTrace&) { return absl::DataLossError("stop"); });
  EXPECT_EQ(stopped.code(), absl::StatusCode::kDataLoss);
}

// Searches start where the last one ended: takes in any order, near and
// far, backwards and forwards, find every trace, and no key between them.
TEST(TraceTableTest, TakesInAnyOrderFindEveryTraceAndNothingBetween) {
  TraceTable table;
  std::vector<core::TraceKey> keys;
  for (const std::string robot : {"a", "b", "c"}) {
    for (uint64_t seq = 2; seq <= 800; seq += 2) {
      table.Add(TraceOf(robot, seq, seq / 20 + 1));
      keys.push_back({robot, seq});
    }
  }
  std::vector<core::TraceKey> order;
  for (size_t i = 0; i < keys.size(); i += 2) order.push_back(keys[i]);
  for (size_t i = keys.size() - 1; i < keys.size(); i -= 2) {
    order.push_back(keys[i]);  // backwards, over the odd positions
  }
  std::mt19937_64 rng(7);
  std::shuffle(order.begin() + order.size() * 3 / 4, order.end(), rng);
  for (const core::TraceKey& key : order) {
    EXPECT_FALSE(table.Take({key.robot_id, key.seq - 1}, key.seq / 20 + 1))
        << key.robot_id << "/" << key.seq - 1;
    EXPECT_FALSE(table.Take({key.robot_id, key.seq + 1}, key.seq / 20 + 1))
        << key.robot_id << "/" << key.seq + 1;
    std::optional<core::MemoryTrace> taken = table.Take(key, key.seq / 20 + 1);
    ASSERT_TRUE(taken.has_value()) << key.robot_id << "/" << key.seq;
    EXPECT_EQ(taken->key(), key);
  }
  EXPECT_EQ(table.AnyLeft(), nullptr);
  EXPECT_FALSE(table.Take({"0", 1}, 1));  // before the first
  EXPECT_FALSE(table.Take({"d", 1}, 1));  // after the last
  EXPECT_FALSE(table.Take({"a", 2}, 1));  // taken already
}

TEST(RecordCodecTest, ATraceRecordWithoutItsCodeHoldsEverythingElse) {
  const core::MemoryTrace trace = TraceOf("r1", 5, 2);
  ASSERT_FALSE(trace.code.empty());
  const std::string key = keys::TraceKey("f", trace.key());
  const std::string whole = EncodeTrace(trace);
  const std::string without = EncodeTraceWithoutCode(trace);
  EXPECT_LT(without.size() + trace.code.size() * sizeof(float),
            whole.size() + 8);
  absl::StatusOr<core::MemoryTrace> decoded = DecodeTrace(key, without);
  ASSERT_TRUE(decoded.ok()) << decoded.status();
  EXPECT_TRUE(decoded->code.empty());
  core::MemoryTrace expected = trace;
  expected.code.clear();
  EXPECT_EQ(testing::Dump(engine::FleetRecord{.pending = {*decoded}}),
            testing::Dump(engine::FleetRecord{.pending = {expected}}));
  // A record of layout 1 still decodes with its code.
  absl::StatusOr<core::MemoryTrace> old = DecodeTrace(key, whole);
  ASSERT_TRUE(old.ok()) << old.status();
  EXPECT_EQ(old->code, trace.code);
}

TEST(RecordCodecTest, ACodeRoundTripsBitForBit) {
  const std::vector<float> code = {0.0f, -1.5f, 3.25e-8f, 1e30f, -0.0f};
  const std::string key = keys::CodeKey("f", {"r1", 5});
  const std::string value = EncodeCode(code);
  EXPECT_EQ(value.size(), code.size() * sizeof(float));
  std::vector<float> decoded = {9.0f};
  ASSERT_TRUE(DecodeCode(key, value, &decoded).ok());
  ASSERT_EQ(decoded.size(), code.size());
  for (size_t i = 0; i < code.size(); ++i) {
    EXPECT_EQ(std::bit_cast<uint32_t>(decoded[i]),
              std::bit_cast<uint32_t>(code[i]))
        << i;
  }
}

TEST(RecordCodecTest, ACodeOfPartialFloatsIsDataLossNamingItsKey) {
  const std::string key = keys::CodeKey("f", {"r1", 5});
  std::vector<float> decoded;
  for (const std::string value : {std::string(), std::string(7, 'x')}) {
    const absl::Status status = DecodeCode(key, value, &decoded);
    EXPECT_EQ(status.code(), absl::StatusCode::kDataLoss) << value.size();
    EXPECT_NE(status.message().find("code[f/r1/5]"), std::string_view::npos)
        << status;
  }
}

}  // namespace
}  // namespace fleetmem::storage
