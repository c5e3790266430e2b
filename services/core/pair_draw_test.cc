#include "services/core/pair_draw.h"

#include <random>
#include <set>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/core/importance_sampler.h"

namespace fleetmem::core {
namespace {

MemoryTrace Trace(const std::string& domain, double x, double y = 0.0) {
  MemoryTrace t;
  t.domain = domain;
  t.place = {.x = x, .y = y};
  return t;
}

std::vector<const MemoryTrace*> Pointers(const std::vector<MemoryTrace>& t) {
  std::vector<const MemoryTrace*> out;
  for (const MemoryTrace& trace : t) out.push_back(&trace);
  return out;
}

TEST(DrawPairsTest, EachAnchorComesWithItsNearestPartnerOfAnotherDomain) {
  // Summer every 10 units, winter every 10 units shifted by 3; each summer
  // trace's nearest winter one is 3 away.
  std::vector<MemoryTrace> traces;
  for (int i = 0; i < 50; ++i) traces.push_back(Trace("summer", 10.0 * i));
  for (int i = 0; i < 50; ++i) traces.push_back(Trace("winter", 10.0 * i + 3));
  const std::vector<double> weights(traces.size(), 1.0);
  std::mt19937_64 rng(7);
  const std::vector<size_t> drawn =
      DrawPairs(Pointers(traces), weights, 40, 5.0, rng);
  ASSERT_EQ(drawn.size(), 40u);
  EXPECT_EQ(std::set<size_t>(drawn.begin(), drawn.end()).size(), 40u);
  for (size_t i = 0; i < drawn.size(); i += 2) {
    const MemoryTrace& a = traces[drawn[i]];
    const MemoryTrace& b = traces[drawn[i + 1]];
    EXPECT_NE(a.domain, b.domain);
    EXPECT_NEAR(std::abs(a.place.x - b.place.x), 3.0, 1e-9);
  }
}

TEST(DrawPairsTest, AnAnchorWithoutAPartnerGoesAlone) {
  // Two summer traces far apart, one winter partner for the first only;
  // a same-domain neighbour is never a partner.
  std::vector<MemoryTrace> traces = {Trace("summer", 0), Trace("summer", 1),
                                     Trace("summer", 1000), Trace("winter", 2)};
  std::mt19937_64 rng(1);
  const std::vector<size_t> drawn = DrawPairs(
      Pointers(traces), std::vector<double>{1.0, 0.0, 1e6, 0.0}, 4, 5.0, rng);
  ASSERT_EQ(drawn.size(), 4u);
  EXPECT_EQ(drawn[0], 2u);  // by far the heaviest, alone
  // Then the other positive-weight anchor, with the winter trace 2 away.
  EXPECT_EQ(drawn[1], 0u);
  EXPECT_EQ(drawn[2], 3u);
  EXPECT_EQ(drawn[3], 1u);
}

TEST(DrawPairsTest, APartnerAcrossACellBorderAndInTwoDimensions) {
  std::vector<MemoryTrace> traces = {Trace("summer", 9.9, 9.9),
                                     Trace("winter", 10.1, 10.2),
                                     Trace("winter", 14.0, 14.0)};
  std::mt19937_64 rng(3);
  const std::vector<size_t> drawn = DrawPairs(
      Pointers(traces), std::vector<double>{1e9, 0.0, 0.0}, 2, 10.0, rng);
  EXPECT_THAT(drawn, ::testing::ElementsAre(0, 1));
}

TEST(DrawPairsTest, WithoutARadiusItIsEq18sDraw) {
  std::vector<MemoryTrace> traces;
  for (int i = 0; i < 30; ++i) {
    traces.push_back(Trace(i % 2 ? "summer" : "winter", i));
  }
  std::vector<double> weights;
  for (int i = 0; i < 30; ++i) weights.push_back(1.0 + i);
  std::mt19937_64 a(5), b(5);
  EXPECT_EQ(DrawPairs(Pointers(traces), weights, 12, 0.0, a),
            SampleWithoutReplacement(weights, 12, b));
  std::mt19937_64 c(5);
  EXPECT_TRUE(DrawPairs({}, {}, 5, 10.0, c).empty());
  EXPECT_TRUE(DrawPairs(Pointers(traces), weights, 0, 10.0, c).empty());
}

}  // namespace
}  // namespace fleetmem::core
