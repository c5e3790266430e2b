#include "tools/eval/lifelong_protocol.h"

#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::eval::lifelong {
namespace {

using ::testing::ElementsAre;

TEST(LifelongProtocolTest, SplitChecksEveryPlace) {
  const Split split = SplitRoute(12);
  EXPECT_THAT(split.area, ElementsAre(0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2));
  EXPECT_THAT(split.held_out,
              ElementsAre(false, false, false, true, false, false, false, true,
                          false, false, false, true));
  EXPECT_THAT(split.Places(1, true), ElementsAre(7));
  EXPECT_THAT(split.Places(2, false), ElementsAre(8, 9, 10));
  // Areas of unequal size: the 4th place of each area, counted within it.
  const Split uneven = SplitRoute(10);
  EXPECT_THAT(uneven.area, ElementsAre(0, 0, 0, 0, 1, 1, 1, 2, 2, 2));
  EXPECT_THAT(uneven.Places(0, true), ElementsAre(3));
  EXPECT_TRUE(uneven.Places(1, true).empty());
}

TEST(LifelongProtocolTest, RecallAndWrOfAHandRankedMap) {
  // Two queries against a map of 10 places.
  Eigen::MatrixXf sim = Eigen::MatrixXf::Zero(2, 10);
  // Query at place 5: places 0 and 9 rank above place 4 (correct, |4-5| <= 2).
  sim(0, 0) = 0.9f;
  sim(0, 9) = 0.8f;
  sim(0, 4) = 0.7f;
  // Query at place 1: place 2 first.
  sim(1, 2) = 0.5f;
  const Score s = ScoreQueries(sim, {5, 1});
  EXPECT_THAT(s.recall, ElementsAre(0.5, 0.5, 1, 1, 1, 1));
  EXPECT_DOUBLE_EQ(s.wr, 0.5 * 0.5 + 0.1 * (0.5 + 4));
}

TEST(LifelongProtocolTest, TiesGoToTheEarlierMapPlace) {
  Eigen::MatrixXf sim = Eigen::MatrixXf::Zero(1, 20);
  // All equal: ranks 1..6 are places 0..5; the query at place 9 is not
  // found, the one at place 7 is found at rank 6 (place 5).
  EXPECT_EQ(ScoreQueries(sim, {9}).wr, 0.0);
  const Score s = ScoreQueries(sim, {7});
  EXPECT_THAT(s.recall, ElementsAre(0, 0, 0, 0, 0, 1));
}

TEST(LifelongProtocolTest, ScoreAreasSearchesTheWholeSummerMap) {
  // 12 places; descriptors one-hot on the place: every held-out winter
  // query (3, 7, 11) finds its own summer frame first.
  const Split split = SplitRoute(12);
  const Eigen::MatrixXf map = Eigen::MatrixXf::Identity(12, 12);
  const std::vector<Score> scores = ScoreAreas(split, map, map);
  ASSERT_EQ(scores.size(), 3u);
  for (const Score& s : scores) EXPECT_DOUBLE_EQ(s.wr, 1.0);
  // Winter frames that look like the place 4 files further: all wrong.
  Eigen::MatrixXf shifted = Eigen::MatrixXf::Zero(12, 12);
  for (int i = 0; i < 12; ++i) shifted(i, (i + 4) % 12) = 1;
  for (const Score& s : ScoreAreas(split, map, shifted))
    EXPECT_EQ(s.recall[0], 0.0);
}

TEST(LifelongProtocolTest, ChanceLevelByCounting) {
  // 12 places, queries 3, 7, 11 with 5, 5 and 3 correct entries.
  const Score c = ChanceScore(SplitRoute(12));
  EXPECT_NEAR(c.recall[0], (5 + 5 + 3) / 36.0, 1e-12);
  auto none2 = [](double m) { return (12 - m) * (11 - m) / (12.0 * 11); };
  EXPECT_NEAR(c.recall[1], 1 - (2 * none2(5) + none2(3)) / 3, 1e-12);
  EXPECT_NEAR(
      c.wr,
      0.5 * c.recall[0] + 0.1 * (c.recall[1] + c.recall[2] + c.recall[3] +
                                 c.recall[4] + c.recall[5]),
      1e-12);
}

TEST(LifelongProtocolTest, SequencesResolveWhatOneFrameCannot) {
  // Query 15's own frame resembles map place 3 more than place 15; the
  // frames before it match their own places.
  Eigen::MatrixXf frames = Eigen::MatrixXf::Constant(20, 20, 0.2f);
  for (int i = 0; i < 20; ++i) frames(i, i) = 0.9f;
  frames(15, 3) = 1.0f;
  Eigen::Index single, seq;
  frames.row(15).maxCoeff(&single);
  EXPECT_EQ(single, 3);
  SequenceSimilarity(frames, 5).row(15).maxCoeff(&seq);
  EXPECT_EQ(seq, 15);
}

TEST(LifelongProtocolTest, SummaryFromHandMadeCurves) {
  // areas[t][a].wr = 0.1 t + 0.01 a.
  std::vector<std::vector<Score>> areas(kDomains, std::vector<Score>(kAreas));
  for (int t = 0; t < kDomains; ++t)
    for (int a = 0; a < kAreas; ++a) areas[t][a].wr = 0.1 * t + 0.01 * a;
  const Summary s = Summarise(areas);
  EXPECT_NEAR(s.wr_final, 0.51, 1e-12);
  EXPECT_NEAR(s.ae, (0.3 + 0.41 + 0.52) / 3, 1e-12);
  EXPECT_NEAR(s.ra, (0.4 + (0.5 + 0.51) / 2) / 2, 1e-12);
  EXPECT_NEAR(s.unseen, (0.01 + 0.11 + 0.21 + 0.315 + 0.42) / 5, 1e-12);
}

}  // namespace
}  // namespace fleetmem::eval::lifelong
