#include "services/core/seq_set.h"

#include <limits>
#include <random>
#include <set>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

using ::testing::ElementsAre;
using Interval = SeqSet::Interval;

TEST(SeqSetTest, EmptySet) {
  SeqSet set;
  EXPECT_EQ(set.size(), 0u);
  EXPECT_EQ(set.max(), 0u);
  EXPECT_FALSE(set.Contains(0));
  EXPECT_TRUE(set.Intervals().empty());
}

TEST(SeqSetTest, InOrderInsertsStayOneInterval) {
  SeqSet set;
  for (uint64_t seq = 1; seq <= 1000; ++seq) ASSERT_TRUE(set.Insert(seq));
  EXPECT_THAT(set.Intervals(), ElementsAre(Interval{1, 1000}));
  EXPECT_EQ(set.size(), 1000u);
  EXPECT_EQ(set.max(), 1000u);
}

TEST(SeqSetTest, DetectsDuplicates) {
  SeqSet set;
  EXPECT_TRUE(set.Insert(5));
  EXPECT_FALSE(set.Insert(5));
  EXPECT_TRUE(set.Insert(6));
  EXPECT_FALSE(set.Insert(5));
  EXPECT_FALSE(set.Insert(6));
  EXPECT_EQ(set.size(), 2u);
}

TEST(SeqSetTest, MergesIntervalsWhenGapsFill) {
  SeqSet set;
  for (uint64_t seq : {1, 2, 3, 7, 8, 5}) ASSERT_TRUE(set.Insert(seq));
  EXPECT_THAT(set.Intervals(),
              ElementsAre(Interval{1, 3}, Interval{5, 5}, Interval{7, 8}));
  EXPECT_TRUE(set.Insert(4));
  EXPECT_THAT(set.Intervals(), ElementsAre(Interval{1, 5}, Interval{7, 8}));
  EXPECT_TRUE(set.Insert(6));
  EXPECT_THAT(set.Intervals(), ElementsAre(Interval{1, 8}));
  EXPECT_EQ(set.size(), 8u);
  EXPECT_TRUE(set.Contains(4));
  EXPECT_FALSE(set.Contains(9));
  EXPECT_FALSE(set.Contains(0));
}

TEST(SeqSetTest, ExtremeValues) {
  constexpr uint64_t kMax = std::numeric_limits<uint64_t>::max();
  SeqSet set;
  EXPECT_TRUE(set.Insert(kMax));
  EXPECT_TRUE(set.Insert(0));
  EXPECT_TRUE(set.Insert(kMax - 1));
  EXPECT_THAT(set.Intervals(),
              ElementsAre(Interval{0, 0}, Interval{kMax - 1, kMax}));
  EXPECT_EQ(set.max(), kMax);
  EXPECT_FALSE(set.Insert(kMax));
}

TEST(SeqSetTest, FromIntervalsMergesOverlapsAndAdjacent) {
  const SeqSet set =
      SeqSet::FromIntervals({{10, 12}, {1, 3}, {2, 5}, {6, 6}, {20, 20}});
  EXPECT_THAT(set.Intervals(),
              ElementsAre(Interval{1, 6}, Interval{10, 12}, Interval{20, 20}));
  EXPECT_EQ(set.size(), 10u);
  EXPECT_EQ(set.max(), 20u);
}

TEST(SeqSetTest, RandomInsertsMatchReferenceAndRoundTrip) {
  std::mt19937_64 rng(7);
  SeqSet set;
  std::set<uint64_t> reference;
  for (int step = 0; step < 2000; ++step) {
    const uint64_t seq = rng() % 500;
    EXPECT_EQ(set.Insert(seq), reference.insert(seq).second) << seq;
  }
  EXPECT_EQ(set.size(), reference.size());
  EXPECT_EQ(set.max(), *reference.rbegin());
  for (uint64_t seq = 0; seq < 510; ++seq) {
    ASSERT_EQ(set.Contains(seq), reference.contains(seq)) << seq;
  }
  // Intervals are disjoint, sorted and never adjacent.
  const std::vector<Interval> intervals = set.Intervals();
  for (size_t i = 1; i < intervals.size(); ++i) {
    EXPECT_GT(intervals[i].first, intervals[i - 1].second + 1);
  }
  const SeqSet restored = SeqSet::FromIntervals(intervals);
  EXPECT_EQ(restored.Intervals(), intervals);
  EXPECT_EQ(restored.size(), set.size());
  EXPECT_EQ(restored.max(), set.max());
}

}  // namespace
}  // namespace fleetmem::core
