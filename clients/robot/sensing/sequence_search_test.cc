#include "clients/robot/sensing/sequence_search.h"

#include <random>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::robot {
namespace {

using ::testing::ElementsAre;

constexpr double kStep = 10.0;  // place units between frames

// A robot driving a 1-D route at places 1000, 1010, ...: each frame's
// candidates are `k` places, the true one at `true_rank` (0-based; -1: not
// among them, a gap) and the others scattered over the route, nearest
// first by distance 0.1, 0.2, ...
std::vector<SequenceFrame> Drive(size_t frames, size_t k,
                                 const std::vector<int>& true_rank,
                                 uint32_t seed) {
  std::mt19937 random(seed);
  std::uniform_real_distribution<double> anywhere(0.0, 25000.0);
  std::vector<SequenceFrame> drive;
  for (size_t i = 0; i < frames; ++i) {
    SequenceFrame frame;
    frame.travelled = i == 0 ? 0.0 : kStep;
    for (size_t c = 0; c < k; ++c) {
      const bool truth = static_cast<int>(c) == true_rank[i];
      frame.candidates.push_back(
          {.place = {.x =
                         truth ? 1000.0 + kStep * double(i) : anywhere(random)},
           .distance = 0.1f * float(c + 1)});
    }
    drive.push_back(std::move(frame));
  }
  return drive;
}

TEST(SequenceSearchTest, OneFrameKeepsTheServersOrder) {
  const auto drive = Drive(5, 4, {2, 2, 2, 2, 2}, 1);
  EXPECT_THAT(RankBySequence(drive, {.length = 1}), ElementsAre(0, 1, 2, 3));
  EXPECT_THAT(RankBySequence(std::span(drive).last(1), {.length = 10}),
              ElementsAre(0, 1, 2, 3));
  EXPECT_TRUE(RankBySequence({}, {}).empty());
}

TEST(SequenceSearchTest, AConsistentPathOutranksTheNearestSingleFrame) {
  // The true place is third in every frame; the nearest are scattered.
  const auto drive = Drive(10, 6, std::vector<int>(10, 2), 2);
  const std::vector<size_t> ranked = RankBySequence(drive, {.length = 10});
  ASSERT_EQ(ranked.size(), 6u);
  EXPECT_EQ(ranked.front(), 2u);
  // Fewer frames than the length: the path over what there is.
  EXPECT_EQ(RankBySequence(std::span(drive).first(3), {.length = 10}).front(),
            2u);
}

TEST(SequenceSearchTest, SequencePlacesAreTheReRankedCandidatesPlaces) {
  const auto drive = Drive(10, 6, std::vector<int>(10, 2), 2);
  const std::vector<core::Place> places =
      SequencePlaces(drive, {.length = 10}, 3);
  ASSERT_EQ(places.size(), 3u);
  EXPECT_EQ(places[0].x, 1000.0 + kStep * 9);  // the true place, first
  EXPECT_EQ(SequencePlaces(drive, {.length = 10}, 100).size(), 6u);
  EXPECT_TRUE(SequencePlaces({}, {}, 3).empty());
}

TEST(SequenceSearchTest, APathCrossesFramesWhosePlaceWasForgotten) {
  // Frames 2, 3, 5 and 6 hold no trace of the true place (forgotten, or
  // another robot's gap); it is fourth of six in the rest.
  const std::vector<int> ranks = {3, 3, -1, -1, 3, -1, -1, 3, 3, 3};
  const auto drive = Drive(10, 6, ranks, 3);
  EXPECT_EQ(RankBySequence(drive, {.length = 10}).front(), 3u);
}

TEST(SequenceSearchTest, AChainAtAnotherSpeedIsNotConsistent) {
  // A wrong chain of candidates moving 30 units a frame (the robot moves
  // 10) nearer than the true place in every frame: the search follows the
  // robot's travelled distance, not the chain.
  auto drive = Drive(10, 3, std::vector<int>(10, 1), 4);
  for (size_t i = 0; i < drive.size(); ++i) {
    drive[i].candidates[0].place.x = 5000.0 + 30.0 * double(i);
  }
  EXPECT_EQ(RankBySequence(drive, {.length = 10, .tolerance = 5.0}).front(),
            1u);
  // Told the robot moves 30 a frame, it follows the chain instead.
  for (SequenceFrame& frame : drive) frame.travelled *= 3.0;
  EXPECT_EQ(RankBySequence(drive, {.length = 10, .tolerance = 5.0}).front(),
            0u);
}

TEST(SequenceSearchTest, OnlyTheLastLengthFramesCount) {
  // Frames 0-6: the true place (rank 1) consistent; 7-9: a consistent
  // false chain nearest. Over 3 frames the chain wins, over 10 the truth.
  auto drive = Drive(10, 3, std::vector<int>(10, 1), 5);
  for (size_t i = 7; i < 10; ++i) {
    drive[i].candidates[0].place.x = 9000.0 + kStep * double(i);
  }
  EXPECT_EQ(RankBySequence(drive, {.length = 3}).front(), 0u);
  EXPECT_EQ(RankBySequence(drive, {.length = 10}).front(), 1u);
}

TEST(SequenceSearchTest, AFrameOfEqualDistancesAddsNothing) {
  SequenceFrame flat;
  flat.candidates = {{.place = {.x = 0}, .distance = 0.5f},
                     {.place = {.x = 100}, .distance = 0.5f}};
  SequenceFrame next = flat;
  next.travelled = kStep;
  next.candidates[0].place.x = 10;
  next.candidates[1].place.x = 110;
  const std::vector<SequenceFrame> drive = {flat, next};
  EXPECT_THAT(RankBySequence(drive, {.length = 2}), ElementsAre(0, 1));
}

TEST(SequenceWindowTest, KeepsTheLastFramesAndTheDistanceTravelled) {
  SequenceWindow window(3);
  for (int i = 0; i < 5; ++i) {
    window.Add({.x = 3.0 * i, .y = 4.0 * i},
               {{.place = {.x = double(i)}, .distance = 0.1f}});
  }
  ASSERT_EQ(window.frames().size(), 3u);
  EXPECT_EQ(window.frames().front().candidates[0].place.x, 2.0);
  EXPECT_DOUBLE_EQ(window.frames().back().travelled, 5.0);
  window.Clear();
  EXPECT_TRUE(window.frames().empty());
  window.Add({.x = 100}, {});
  EXPECT_EQ(window.frames().front().travelled, 0.0);
}

}  // namespace
}  // namespace fleetmem::robot
