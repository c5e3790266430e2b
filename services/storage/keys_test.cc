#include "services/storage/keys.h"

#include <string>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::storage::keys {
namespace {

TEST(KeysTest, BigEndianIdsSortNumerically) {
  const std::vector<uint64_t> ids = {1,     2,          255,       256,
                                     65535, 1ull << 40, UINT64_MAX};
  for (size_t i = 1; i < ids.size(); ++i) {
    EXPECT_LT(EventKey("f", ids[i - 1]), EventKey("f", ids[i])) << ids[i];
    EXPECT_LT(ClusterKey("f", ids[i - 1]), ClusterKey("f", ids[i])) << ids[i];
  }
}

TEST(KeysTest, TraceKeysSortByRobotThenSeq) {
  EXPECT_LT(TraceKey("f", {"a", 300}), TraceKey("f", {"a1", 1}));
  EXPECT_LT(TraceKey("f", {"a", 2}), TraceKey("f", {"a", 256}));
  EXPECT_LT(PendingKey("f", {"a", UINT64_MAX}), PendingKey("f", {"b", 0}));
}

TEST(KeysTest, FleetRangesDoNotOverlapForPrefixIds) {
  // "f" is a prefix of "f1" and "f.x": none of their keys may fall in f's
  // range [Prefix, PrefixEnd).
  for (Tag tag : kFleetTags) {
    const std::string begin = Prefix(tag, "f");
    const std::string end = PrefixEnd(tag, "f");
    const std::vector<std::string> others = {MetaKey("f1"),
                                             PendingKey("f1", {"r", 1}),
                                             TraceKey("f.x", {"", 0}),
                                             ClusterKey("f-", 0),
                                             RobotKey("f1", ""),
                                             EventKey("f:", 1)};
    for (const std::string& key : others) {
      EXPECT_FALSE(begin <= key && key < end) << Describe(key);
    }
    EXPECT_LT(begin, end);
  }
  EXPECT_LE(Prefix(Tag::kEvent, "f"), EventKey("f", 0));
  EXPECT_LT(EventKey("f", UINT64_MAX), PrefixEnd(Tag::kEvent, "f"));
}

TEST(KeysTest, ParseRoundTrips) {
  const std::string key = TraceKey("fleet-1", {"robot.7", 4097});
  const std::optional<ParsedKey> parsed = Parse(key);
  ASSERT_TRUE(parsed.has_value());
  EXPECT_EQ(parsed->tag, Tag::kTrace);
  EXPECT_EQ(parsed->fleet_id, "fleet-1");
  const std::optional<core::TraceKey> trace_key =
      ParseTraceSuffix(parsed->suffix);
  ASSERT_TRUE(trace_key.has_value());
  EXPECT_EQ(*trace_key, (core::TraceKey{"robot.7", 4097}));

  const std::string event_key = EventKey("g", 77);  // Parse returns views
  const std::optional<ParsedKey> event = Parse(event_key);
  ASSERT_TRUE(event.has_value());
  EXPECT_EQ(ParseIdSuffix(event->suffix), 77u);

  EXPECT_FALSE(Parse("").has_value());
  EXPECT_FALSE(Parse("xf\0").has_value());
  EXPECT_FALSE(Parse("mf").has_value());  // no separator
  EXPECT_FALSE(ParseIdSuffix("1234567").has_value());
  EXPECT_FALSE(ParseTraceSuffix("r12345678").has_value());  // no separator
}

TEST(KeysTest, DescribeNamesTheRecord) {
  struct Case {
    std::string key;
    std::string want;
  };
  const std::vector<Case> cases = {
      {MetaKey("f1"), "meta[f1]"},
      {PendingKey("f1", {"r2", 17}), "pending[f1/r2/17]"},
      {TraceKey("f1", {"r2", 17}), "trace[f1/r2/17]"},
      {ClusterKey("f1", 5), "cluster[f1/5]"},
      {RobotKey("f1", "r2"), "robot[f1/r2]"},
      {EventKey("f1", 9), "event[f1/9]"},
      {std::string("z\x01"), "key \"z\\x01\""},
  };
  for (const Case& c : cases) EXPECT_EQ(Describe(c.key), c.want);
}

}  // namespace
}  // namespace fleetmem::storage::keys
