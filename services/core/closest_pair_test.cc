#include "services/core/closest_pair.h"

#include <algorithm>
#include <map>
#include <random>
#include <span>
#include <string>
#include <string_view>
#include <tuple>

#include "absl/status/status.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

// O(K^2) reference: smallest (distance, a, b) over all pairs a < b, with the
// same distance formula the tracker uses.
std::optional<ClosestPairTracker::Pair> BruteForce(
    const std::map<uint64_t, Eigen::VectorXf>& points) {
  std::optional<ClosestPairTracker::Pair> best;
  for (auto i = points.begin(); i != points.end(); ++i) {
    for (auto j = std::next(i); j != points.end(); ++j) {
      const double d = static_cast<double>((i->second - j->second).norm());
      if (!best || std::tie(d, i->first, j->first) <
                       std::tie(best->distance, best->a, best->b)) {
        best = ClosestPairTracker::Pair{i->first, j->first, d};
      }
    }
  }
  return best;
}

void ExpectSame(const std::optional<ClosestPairTracker::Pair>& got,
                const std::optional<ClosestPairTracker::Pair>& want, int step) {
  ASSERT_EQ(got.has_value(), want.has_value()) << "step " << step;
  if (!want) return;
  EXPECT_EQ(got->a, want->a) << "step " << step;
  EXPECT_EQ(got->b, want->b) << "step " << step;
  EXPECT_EQ(got->distance, want->distance) << "step " << step;
}

// A point of `dimension` standard normal coordinates.
Eigen::VectorXf Gaussian(std::mt19937_64& rng, int dimension) {
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  Eigen::VectorXf p(dimension);
  for (int d = 0; d < dimension; ++d) p[d] = gauss(rng);
  return p;
}

TEST(ClosestPairTrackerTest, FewerThanTwoPoints) {
  ClosestPairTracker tracker;
  EXPECT_FALSE(tracker.Closest().has_value());
  tracker.Insert(1, Eigen::Vector2f(0, 0));
  EXPECT_FALSE(tracker.Closest().has_value());
  tracker.Insert(2, Eigen::Vector2f(3, 4));
  ASSERT_TRUE(tracker.Closest().has_value());
  EXPECT_EQ(tracker.Closest()->a, 1u);
  EXPECT_EQ(tracker.Closest()->b, 2u);
  EXPECT_DOUBLE_EQ(tracker.Closest()->distance, 5.0);
  tracker.Remove(1);
  EXPECT_FALSE(tracker.Closest().has_value());
  EXPECT_EQ(tracker.size(), 1u);
  tracker.Remove(42);  // absent: no-op
  EXPECT_EQ(tracker.size(), 1u);
}

TEST(ClosestPairTrackerTest, TiesGoToSmallestIds) {
  ClosestPairTracker tracker;
  tracker.Insert(9, Eigen::Vector2f(10, 0));
  tracker.Insert(7, Eigen::Vector2f(11, 0));
  tracker.Insert(5, Eigen::Vector2f(0, 0));
  tracker.Insert(8, Eigen::Vector2f(1, 0));
  const auto pair = tracker.Closest();
  ASSERT_TRUE(pair.has_value());
  EXPECT_EQ(pair->a, 5u);
  EXPECT_EQ(pair->b, 8u);
}

// Random inserts and removals, compared against the O(K^2) reference after
// every step. `grid` coordinates make many exact distance ties.
void RunRandomSequence(int dimension, bool grid, uint64_t seed, int steps) {
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<int> cell(0, 6);
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  ClosestPairTracker tracker;
  std::map<uint64_t, Eigen::VectorXf> reference;
  uint64_t next_id = 0;
  for (int step = 0; step < steps; ++step) {
    const bool insert = reference.size() < 3 || rng() % 100 < 55;
    if (insert) {
      Eigen::VectorXf p(dimension);
      for (int d = 0; d < dimension; ++d) {
        p[d] = grid ? static_cast<float>(cell(rng)) : gauss(rng);
      }
      const uint64_t id = next_id += 1 + rng() % 3;
      tracker.Insert(id, p);
      reference[id] = p;
    } else {
      auto it = reference.begin();
      std::advance(it, rng() % reference.size());
      tracker.Remove(it->first);
      reference.erase(it);
    }
    ASSERT_EQ(tracker.size(), reference.size());
    ExpectSame(tracker.Closest(), BruteForce(reference), step);
    if (::testing::Test::HasFailure()) return;
  }
}

TEST(ClosestPairTrackerTest, MatchesBruteForceOnGridWithTies) {
  for (uint64_t seed = 1; seed <= 3; ++seed)
    RunRandomSequence(2, true, seed, 400);
}

TEST(ClosestPairTrackerTest, MatchesBruteForceInHighDimension) {
  RunRandomSequence(32, false, 17, 600);
}

TEST(ClosestPairTrackerTest, RemovingDownToEmpty) {
  ClosestPairTracker tracker;
  std::map<uint64_t, Eigen::VectorXf> reference;
  std::mt19937_64 rng(5);
  for (uint64_t id = 0; id < 60; ++id) {
    const Eigen::VectorXf p = Gaussian(rng, 3);
    tracker.Insert(id, p);
    reference[id] = p;
  }
  // Always remove a member of the current closest pair, as forgetting does.
  for (int step = 0; step < 60; ++step) {
    const auto pair = tracker.Closest();
    ExpectSame(pair, BruteForce(reference), step);
    if (HasFailure()) return;
    const uint64_t victim = pair ? pair->a : reference.begin()->first;
    tracker.Remove(victim);
    reference.erase(victim);
  }
  EXPECT_EQ(tracker.size(), 0u);
}

// Above exact_below the tracker answers through its HNSW graph: the pair is
// approximate, but the bookkeeping must stay consistent (sizes, removals down
// to the exact regime again) and the pair close to the true one.
TEST(ClosestPairTrackerTest, GraphModeAgreesWithBruteForceMostly) {
  ClosestPairOptions options;
  options.exact_below = 64;
  ClosestPairTracker tracker(options);
  std::map<uint64_t, Eigen::VectorXf> reference;
  std::mt19937_64 rng(23);
  uint64_t next_id = 1;
  auto insert = [&] {
    const Eigen::VectorXf p = Gaussian(rng, 16);
    tracker.Insert(next_id, p);
    reference[next_id++] = p;
  };
  for (int i = 0; i < 300; ++i) insert();
  EXPECT_TRUE(tracker.approximate());
  int same = 0, steps = 0;
  // Forgetting-like churn: insert a few, remove a member of the closest pair.
  for (int step = 0; step < 200; ++step) {
    insert();
    const auto got = tracker.Closest();
    const auto want = BruteForce(reference);
    ASSERT_TRUE(got.has_value());
    ++steps;
    if (got->a == want->a && got->b == want->b) ++same;
    // Never closer than the true closest pair, and a real pair of points.
    EXPECT_GE(got->distance, want->distance);
    EXPECT_FLOAT_EQ(static_cast<float>(got->distance),
                    (reference.at(got->a) - reference.at(got->b)).norm());
    tracker.Remove(got->a);
    reference.erase(got->a);
    ASSERT_EQ(tracker.size(), reference.size());
  }
  EXPECT_GE(same, steps * 9 / 10) << same << " of " << steps;
  // Back below exact_below / 2: exact again, and exactly right.
  while (reference.size() > 20) {
    const uint64_t id = reference.begin()->first;
    tracker.Remove(id);
    reference.erase(id);
  }
  EXPECT_FALSE(tracker.approximate());
  ExpectSame(tracker.Closest(), BruteForce(reference), -1);
  // A copy answers like the original.
  ClosestPairTracker copy = tracker;
  ExpectSame(copy.Closest(), tracker.Closest(), -2);
}

// In graph mode the graph holds each point (the entries keep none); every
// way in and out of that mode gives the points back as inserted, and a copy
// made in graph mode answers like the original through later changes.
TEST(ClosestPairTrackerTest, PointsSurviveEveryModeChangeAndCopy) {
  ClosestPairOptions options;
  options.exact_below = 32;
  ClosestPairTracker tracker(options);
  std::map<uint64_t, Eigen::VectorXf> reference;
  std::mt19937_64 rng(37);
  auto expect_points = [&](const ClosestPairTracker& t, int step) {
    for (const auto& [id, p] : reference) {
      const std::span<const float> got = t.point(id);
      ASSERT_EQ(got.size(), static_cast<size_t>(p.size())) << step;
      EXPECT_TRUE(std::equal(got.begin(), got.end(), p.begin())) << step;
    }
    EXPECT_TRUE(t.point(999999).empty());
  };
  for (uint64_t id = 1; id <= 80; ++id) {
    const Eigen::VectorXf p = Gaussian(rng, 12);
    tracker.Insert(id, p);
    reference[id] = p;
  }
  ASSERT_TRUE(tracker.approximate());
  expect_points(tracker, 0);
  ClosestPairTracker copy = tracker;
  EXPECT_TRUE(copy.approximate());
  expect_points(copy, 1);
  for (int step = 0; step < 70; ++step) {
    ExpectSame(copy.Closest(), tracker.Closest(), step);
    const auto pair = tracker.Closest();
    ASSERT_TRUE(pair.has_value());
    tracker.Remove(pair->a);
    copy.Remove(pair->a);
    reference.erase(pair->a);
  }
  // 10 points left: the graph was dropped and the points moved back.
  EXPECT_FALSE(tracker.approximate());
  EXPECT_FALSE(copy.approximate());
  expect_points(tracker, 2);
  expect_points(copy, 3);
  ExpectSame(tracker.Closest(), BruteForce(reference), 4);
}

std::string Saved(const ClosestPairTracker& tracker) {
  std::string bytes;
  ByteWriter out([&bytes](std::span<const char> data) {
    bytes.append(data.data(), data.size());
  });
  tracker.Save(out);
  return bytes;
}

// A loaded tracker gives the same pairs as the saved one through the same
// later inserts and removals, exact and in graph mode.
TEST(ClosestPairTrackerTest, SavedTrackerLoadsToTheSamePairs) {
  for (size_t exact_below : {size_t{1000}, size_t{16}}) {
    ClosestPairOptions options;
    options.exact_below = exact_below;
    ClosestPairTracker tracker(options);
    std::mt19937_64 rng(29);
    auto point = [&] { return Gaussian(rng, 8); };
    for (uint64_t id = 1; id <= 120; ++id) tracker.Insert(id, point());
    for (uint64_t id = 3; id <= 120; id += 9) tracker.Remove(id);
    ClosestPairTracker loaded(options);
    const std::string bytes = Saved(tracker);
    ByteReader in(bytes);
    ASSERT_TRUE(loaded.Load(in).ok());
    EXPECT_EQ(in.remaining(), 0u);
    EXPECT_EQ(loaded.size(), tracker.size());
    EXPECT_EQ(loaded.approximate(), tracker.approximate());
    for (int step = 0; step < 60; ++step) {
      ExpectSame(loaded.Closest(), tracker.Closest(), step);
      const auto pair = tracker.Closest();
      ASSERT_TRUE(pair.has_value());
      tracker.Remove(pair->a);
      loaded.Remove(pair->a);
      const Eigen::VectorXf p = point();
      tracker.Insert(1000 + step, p);
      loaded.Insert(1000 + step, p);
    }
    // Into a used tracker, or from cut bytes: an error, nothing kept.
    ByteReader again(bytes);
    EXPECT_FALSE(loaded.Load(again).ok());
    for (size_t cut :
         {size_t{0}, size_t{10}, bytes.size() / 2, bytes.size() - 1}) {
      ClosestPairTracker cut_tracker(options);
      ByteReader part(std::string_view(bytes).substr(0, cut));
      EXPECT_EQ(cut_tracker.Load(part).code(), absl::StatusCode::kDataLoss)
          << "cut at " << cut;
      EXPECT_EQ(cut_tracker.size(), 0u);
    }
  }
}

// Whatever byte is damaged, Load refuses it or the tracker stays usable
// (ASan runs this): neighbours, keepers and graph slots are checked.
TEST(ClosestPairTrackerTest, DamagedSnapshotIsRefusedOrSafeToUse) {
  ClosestPairOptions options;
  options.exact_below = 16;
  ClosestPairTracker tracker(options);
  std::mt19937_64 rng(31);
  for (uint64_t id = 1; id <= 60; ++id) {
    const Eigen::VectorXf p = Gaussian(rng, 4);
    tracker.Insert(id, p);
  }
  tracker.Remove(7);
  const std::string bytes = Saved(tracker);
  std::uniform_int_distribution<size_t> position(0, bytes.size() - 1);
  std::uniform_int_distribution<int> value(0, 255);
  int refused = 0;
  for (int trial = 0; trial < 300; ++trial) {
    std::string damaged = bytes;
    damaged[position(rng)] = static_cast<char>(value(rng));
    ClosestPairTracker loaded(options);
    ByteReader in(damaged);
    if (!loaded.Load(in).ok()) {
      ++refused;
      continue;
    }
    for (int step = 0; step < 5; ++step) {
      const auto pair = loaded.Closest();
      if (!pair) break;
      loaded.Remove(pair->a);
      loaded.Insert(500 + step, Eigen::VectorXf::Zero(4));
    }
  }
  EXPECT_GT(refused, 0);
}

}  // namespace
}  // namespace fleetmem::core
