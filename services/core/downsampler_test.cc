#include "services/core/downsampler.h"

#include <cmath>
#include <limits>
#include <set>
#include <string>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

using ::testing::ElementsAre;
using ::testing::UnorderedElementsAre;

MemoryTrace Trace(uint64_t seq, float reward, int64_t timestamp_ns) {
  MemoryTrace trace;
  trace.robot_id = "r";
  trace.seq = seq;
  trace.reward = reward;
  trace.timestamp_ns = timestamp_ns;
  return trace;
}

std::vector<uint64_t> Seqs(const std::vector<MemoryTrace>& traces) {
  std::vector<uint64_t> seqs;
  for (const MemoryTrace& t : traces) seqs.push_back(t.seq);
  return seqs;
}

TEST(DownsampleByRewardTest, KeepsHighestRewards) {
  std::vector<MemoryTrace> traces = {Trace(1, 0.1f, 1), Trace(2, 0.9f, 2),
                                     Trace(3, 0.5f, 3), Trace(4, 0.7f, 4),
                                     Trace(5, 0.2f, 5)};
  const std::vector<MemoryTrace> dropped = DownsampleByReward(traces, 3);
  EXPECT_THAT(Seqs(traces), ElementsAre(2, 4, 3));  // highest reward first
  EXPECT_THAT(Seqs(dropped), UnorderedElementsAre(1, 5));
}

TEST(DownsampleByRewardTest, TiesGoToNewestThenLargestSeq) {
  std::vector<MemoryTrace> traces = {Trace(1, 0.5f, 100), Trace(2, 0.5f, 300),
                                     Trace(3, 0.5f, 200), Trace(4, 0.5f, 300),
                                     Trace(5, 0.5f, 50)};
  const std::vector<MemoryTrace> dropped = DownsampleByReward(traces, 3);
  EXPECT_THAT(Seqs(traces), ElementsAre(4, 2, 3));
  EXPECT_THAT(Seqs(dropped), UnorderedElementsAre(1, 5));
}

TEST(DownsampleByRewardTest, NothingDroppedWhenSmallEnough) {
  std::vector<MemoryTrace> traces = {Trace(1, 0.1f, 1), Trace(2, 0.9f, 2)};
  EXPECT_TRUE(DownsampleByReward(traces, 2).empty());
  EXPECT_EQ(traces.size(), 2u);
  EXPECT_TRUE(DownsampleByReward(traces, 50).empty());
  EXPECT_EQ(traces.size(), 2u);
}

TEST(DownsampleByRewardTest, NaNRewardIsDroppedFirst) {
  std::vector<MemoryTrace> traces = {
      Trace(1, std::numeric_limits<float>::quiet_NaN(), 9), Trace(2, 0.0f, 1)};
  const std::vector<MemoryTrace> dropped = DownsampleByReward(traces, 1);
  EXPECT_THAT(Seqs(traces), ElementsAre(2));
  EXPECT_THAT(Seqs(dropped), ElementsAre(1));
}

TEST(DownsampleByRewardTest, KeptAndDroppedPartitionTheInput) {
  std::vector<MemoryTrace> traces;
  for (uint64_t i = 0; i < 100; ++i) {
    traces.push_back(Trace(i, static_cast<float>((i * 37) % 11), i));
  }
  const std::vector<MemoryTrace> dropped = DownsampleByReward(traces, 10);
  ASSERT_EQ(traces.size(), 10u);
  ASSERT_EQ(dropped.size(), 90u);
  float min_kept = traces[0].reward;
  for (const MemoryTrace& t : traces) min_kept = std::min(min_kept, t.reward);
  std::set<uint64_t> all;
  for (const MemoryTrace& t : traces) all.insert(t.seq);
  for (const MemoryTrace& t : dropped) {
    EXPECT_LE(t.reward, min_kept);
    all.insert(t.seq);
  }
  EXPECT_EQ(all.size(), 100u);
}

MemoryTrace At(uint64_t seq, const std::string& domain, double x,
               float reward) {
  MemoryTrace trace = Trace(seq, reward, 0);
  trace.domain = domain;
  trace.place.x = x;
  return trace;
}

// Hand-worked: the best reward first (seq 3 at x = 9), then the other
// domain's best (seq 11), then the farthest from what each domain keeps:
// seq 1 (9 m from seq 3) before seq 12 (8 m from seq 11).
TEST(DownsampleAlongPlacesTest, SpreadsOverPlacesAndDomains) {
  std::vector<MemoryTrace> traces = {
      At(1, "summer", 0, 0.1f),  At(2, "summer", 1, 0.2f),
      At(3, "summer", 9, 0.9f),  At(4, "summer", 8, 0.5f),
      At(11, "winter", 2, 0.4f), At(12, "winter", 10, 0.3f)};
  const std::vector<MemoryTrace> dropped = DownsampleAlongPlaces(traces, 4);
  EXPECT_THAT(Seqs(traces), ElementsAre(3, 11, 1, 12));
  EXPECT_THAT(Seqs(dropped), UnorderedElementsAre(2, 4));
}

TEST(DownsampleAlongPlacesTest, TheSurvivorsDoNotDependOnTheInputOrder) {
  std::vector<MemoryTrace> traces;
  for (uint64_t i = 0; i < 30; ++i) {
    traces.push_back(At(i, i % 3 == 0 ? "winter" : "summer",
                        static_cast<double>((i * 7) % 13), 0.5f));
  }
  std::vector<MemoryTrace> reversed(traces.rbegin(), traces.rend());
  DownsampleAlongPlaces(traces, 10);
  DownsampleAlongPlaces(reversed, 10);
  EXPECT_EQ(Seqs(traces), Seqs(reversed));
  EXPECT_EQ(traces.size(), 10u);
}

TEST(DownsampleAlongPlacesTest, NothingDroppedWhenSmallEnough) {
  std::vector<MemoryTrace> traces = {At(1, "a", 0, 1), At(2, "a", 5, 1)};
  EXPECT_TRUE(DownsampleAlongPlaces(traces, 2).empty());
  EXPECT_THAT(Seqs(traces), ElementsAre(1, 2));
}

}  // namespace
}  // namespace fleetmem::core
