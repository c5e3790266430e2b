#include "services/core/importance_sampler.h"

#include <cmath>
#include <limits>
#include <map>
#include <numeric>
#include <random>
#include <set>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

using ::testing::UnorderedElementsAre;

// Pearson chi-square statistic of observed counts against probabilities.
double ChiSquare(const std::vector<int>& observed,
                 const std::vector<double>& probabilities, int trials) {
  double chi2 = 0.0;
  for (size_t i = 0; i < observed.size(); ++i) {
    const double expected = probabilities[i] * trials;
    chi2 += (observed[i] - expected) * (observed[i] - expected) / expected;
  }
  return chi2;
}

TEST(ReplayWeightTest, DecaysWithReplayCount) {
  EXPECT_DOUBLE_EQ(ReplayWeight(2.0f, 0, 0.9, 1e-3), 2.0);
  EXPECT_DOUBLE_EQ(ReplayWeight(2.0f, 3, 0.9, 1e-3), 2.0 * 0.9 * 0.9 * 0.9);
  EXPECT_DOUBLE_EQ(ReplayWeight(2.0f, 3, 0.5, 1e-3), 0.25);
}

TEST(ReplayWeightTest, GammaOneIgnoresReplayCount) {
  EXPECT_DOUBLE_EQ(ReplayWeight(2.0f, 0, 1.0, 1e-3),
                   ReplayWeight(2.0f, 1000, 1.0, 1e-3));
}

TEST(ReplayWeightTest, RewardClampedToFloor) {
  EXPECT_DOUBLE_EQ(ReplayWeight(0.0f, 0, 0.9, 1e-3), 1e-3);
  EXPECT_DOUBLE_EQ(ReplayWeight(-5.0f, 0, 0.9, 1e-3), 1e-3);
  EXPECT_DOUBLE_EQ(
      ReplayWeight(std::numeric_limits<float>::quiet_NaN(), 0, 0.9, 1e-3),
      1e-3);
  EXPECT_DOUBLE_EQ(ReplayWeight(0.0f, 1, 0.5, 1e-3), 0.5e-3);
}

TEST(SampleWithoutReplacementTest, DistinctAndClamped) {
  std::mt19937_64 rng(1);
  const std::vector<double> weights = {1, 5, 0.1, 2, 3, 8, 1e-6};
  for (size_t count : {0u, 1u, 3u, 7u, 100u}) {
    const std::vector<size_t> drawn =
        SampleWithoutReplacement(weights, count, rng);
    EXPECT_EQ(drawn.size(), std::min<size_t>(count, weights.size()));
    EXPECT_EQ(std::set<size_t>(drawn.begin(), drawn.end()).size(),
              drawn.size());
    for (size_t i : drawn) EXPECT_LT(i, weights.size());
  }
  EXPECT_TRUE(SampleWithoutReplacement({}, 5, rng).empty());
}

TEST(SampleWithoutReplacementTest, ReproducibleForFixedSeed) {
  const std::vector<double> weights = {1, 2, 3, 4, 5, 6, 7, 8};
  std::mt19937_64 a(5), b(5);
  EXPECT_EQ(SampleWithoutReplacement(weights, 5, a),
            SampleWithoutReplacement(weights, 5, b));
}

TEST(SampleWithoutReplacementTest, FirstDrawProportionalToWeight) {
  const std::vector<double> weights = {1, 2, 3, 4, 10};
  const double total = std::accumulate(weights.begin(), weights.end(), 0.0);
  std::vector<double> p;
  for (double w : weights) p.push_back(w / total);
  constexpr int kTrials = 20000;
  std::mt19937_64 rng(2024);
  std::vector<int> first(weights.size(), 0);
  for (int t = 0; t < kTrials; ++t) {
    ++first[SampleWithoutReplacement(weights, 2, rng)[0]];
  }
  // 4 degrees of freedom: P(chi2 > 18.47) = 0.001.
  EXPECT_LT(ChiSquare(first, p, kTrials), 18.47);
}

TEST(SampleWithoutReplacementTest, DrawOrderIsSuccessiveSampling) {
  // P(first = i, second = j) = w_i / W * w_j / (W - w_i).
  const std::vector<double> weights = {1, 2, 5};
  const double total = 8;
  std::vector<double> p;
  std::vector<std::pair<size_t, size_t>> cells;
  for (size_t i = 0; i < 3; ++i) {
    for (size_t j = 0; j < 3; ++j) {
      if (i == j) continue;
      cells.push_back({i, j});
      p.push_back(weights[i] / total * weights[j] / (total - weights[i]));
    }
  }
  constexpr int kTrials = 20000;
  std::mt19937_64 rng(77);
  std::vector<int> observed(cells.size(), 0);
  for (int t = 0; t < kTrials; ++t) {
    const std::vector<size_t> d = SampleWithoutReplacement(weights, 2, rng);
    for (size_t c = 0; c < cells.size(); ++c) {
      if (cells[c] == std::make_pair(d[0], d[1])) ++observed[c];
    }
  }
  // 5 degrees of freedom: P(chi2 > 20.52) = 0.001.
  EXPECT_LT(ChiSquare(observed, p, kTrials), 20.52);
}

TEST(SampleWithoutReplacementTest, TinyWeightsKeepTheirRatio) {
  // u^(1/w) would underflow to 0 for every item; log keys do not.
  const std::vector<double> weights = {1e-300, 3e-300};
  constexpr int kTrials = 20000;
  std::mt19937_64 rng(8);
  std::vector<int> first(2, 0);
  for (int t = 0; t < kTrials; ++t) {
    ++first[SampleWithoutReplacement(weights, 1, rng)[0]];
  }
  // 1 degree of freedom: P(chi2 > 10.83) = 0.001.
  EXPECT_LT(ChiSquare(first, {0.25, 0.75}, kTrials), 10.83);
}

TEST(SampleWithoutReplacementTest, NonPositiveWeightsComeLast) {
  const std::vector<double> weights = {
      0.0, 1.0, -2.0, 1e-9, std::numeric_limits<double>::quiet_NaN()};
  std::mt19937_64 rng(3);
  for (int t = 0; t < 200; ++t) {
    const std::vector<size_t> drawn = SampleWithoutReplacement(weights, 5, rng);
    ASSERT_EQ(drawn.size(), 5u);
    EXPECT_THAT(std::vector<size_t>(drawn.begin(), drawn.begin() + 2),
                UnorderedElementsAre(1, 3));
  }
}

TEST(SampleWithoutReplacementTest, DecayLowersChanceOfReplayedItems) {
  // Two traces of equal reward; the second was replayed 10 times.
  constexpr int kTrials = 20000;
  for (double gamma : {0.9, 1.0}) {
    const std::vector<double> weights = {ReplayWeight(1.0f, 0, gamma, 1e-3),
                                         ReplayWeight(1.0f, 10, gamma, 1e-3)};
    const double p_replayed = weights[1] / (weights[0] + weights[1]);
    std::mt19937_64 rng(12);
    std::vector<int> first(2, 0);
    for (int t = 0; t < kTrials; ++t) {
      ++first[SampleWithoutReplacement(weights, 1, rng)[0]];
    }
    EXPECT_LT(ChiSquare(first, {1 - p_replayed, p_replayed}, kTrials), 10.83)
        << "gamma " << gamma;
    if (gamma < 1.0) {
      EXPECT_LT(first[1], kTrials * 0.30);  // 0.9^10/(1+0.9^10) = 0.26
    } else {
      EXPECT_GT(first[1], kTrials * 0.47);  // ablation: n is ignored
    }
  }
}

TEST(WeightedSamplerTest, DrawsDistinctSlotsAndKeepsWeights) {
  WeightedSampler sampler;
  const std::vector<double> weights = {1, 5, 0.1, 2, 3, 8, 1e-6};
  for (size_t i = 0; i < weights.size(); ++i) sampler.Set(i, weights[i]);
  EXPECT_EQ(sampler.size(), weights.size());
  std::mt19937_64 rng(3);
  for (size_t count : {0u, 1u, 3u, 7u, 100u}) {
    const std::vector<size_t> drawn = sampler.Draw(count, rng);
    EXPECT_EQ(drawn.size(), std::min<size_t>(count, weights.size()));
    EXPECT_EQ(std::set<size_t>(drawn.begin(), drawn.end()).size(),
              drawn.size());
    for (size_t i : drawn) EXPECT_LT(i, weights.size());
  }
  EXPECT_EQ(sampler.size(), weights.size());
  sampler.Clear(5);
  sampler.Clear(5);  // twice: no-op
  EXPECT_EQ(sampler.size(), weights.size() - 1);
  for (int trial = 0; trial < 200; ++trial) {
    for (size_t slot : sampler.Draw(3, rng)) EXPECT_NE(slot, 5u);
  }
}

// The first two draws of successive sampling from weights {1, 2, 3, 4}: the
// sum tree must give the same joint distribution as the closed form
// P(i then j) = w_i / W * w_j / (W - w_i).
TEST(WeightedSamplerTest, SuccessiveSamplingDistribution) {
  const std::vector<double> weights = {1, 2, 3, 4};
  WeightedSampler sampler;
  for (size_t i = 0; i < weights.size(); ++i) sampler.Set(i, weights[i]);
  std::mt19937_64 rng(11);
  const int trials = 40000;
  std::vector<int> observed(16, 0);
  for (int t = 0; t < trials; ++t) {
    const std::vector<size_t> drawn = sampler.Draw(2, rng);
    ++observed[drawn[0] * 4 + drawn[1]];
  }
  std::vector<int> counts;
  std::vector<double> probabilities;
  for (size_t i = 0; i < 4; ++i) {
    for (size_t j = 0; j < 4; ++j) {
      if (i == j) {
        EXPECT_EQ(observed[i * 4 + j], 0);
        continue;
      }
      counts.push_back(observed[i * 4 + j]);
      probabilities.push_back(weights[i] / 10.0 * weights[j] /
                              (10.0 - weights[i]));
    }
  }
  // 11 degrees of freedom: chi-square 99.9th percentile is 31.3.
  EXPECT_LT(ChiSquare(counts, probabilities, trials), 31.3);
}

TEST(WeightedSamplerTest, ZeroWeightsComeLastAndUniform) {
  WeightedSampler sampler;
  sampler.Set(0, 0.0);
  sampler.Set(1, std::numeric_limits<double>::quiet_NaN());
  sampler.Set(2, 1.0);
  sampler.Set(3, -1.0);
  std::mt19937_64 rng(5);
  std::vector<int> first_zero(4, 0);
  for (int t = 0; t < 3000; ++t) {
    const std::vector<size_t> drawn = sampler.Draw(4, rng);
    ASSERT_EQ(drawn.size(), 4u);
    EXPECT_EQ(drawn[0], 2u);
    ++first_zero[drawn[1]];
  }
  for (size_t slot : {0u, 1u, 3u}) {
    EXPECT_GT(first_zero[slot], 850);
    EXPECT_LT(first_zero[slot], 1150);
  }
  // A weight that becomes positive moves out of the lower tier.
  sampler.Set(0, 5.0);
  EXPECT_EQ(sampler.size(), 4u);
  const std::vector<size_t> drawn = sampler.Draw(2, rng);
  EXPECT_EQ(std::set<size_t>(drawn.begin(), drawn.end()),
            (std::set<size_t>{0, 2}));
}

TEST(WeightedSamplerTest, GrowsAndReusesSlots) {
  WeightedSampler sampler;
  for (size_t i = 0; i < 1000; ++i) sampler.Set(i, 1.0 + i % 7);
  for (size_t i = 0; i < 1000; i += 2) sampler.Clear(i);
  EXPECT_EQ(sampler.size(), 500u);
  std::mt19937_64 rng(9);
  const std::vector<size_t> all = sampler.Draw(1000, rng);
  ASSERT_EQ(all.size(), 500u);
  for (size_t slot : all) EXPECT_EQ(slot % 2, 1u);
  sampler.Set(4000, 2.0);
  EXPECT_EQ(sampler.size(), 501u);
}

// SetAll builds what one Set per slot builds: the same draws follow, and
// later changes act alike, for weights with zeros (trailing too), NaN,
// negatives and an infinity.
TEST(WeightedSamplerTest, SetAllDrawsAsSetsOneByOne) {
  for (size_t n : {0, 1, 5, 16, 17, 1000}) {
    std::mt19937_64 gen(n);
    std::vector<double> weights(n);
    for (size_t i = 0; i < n; ++i) {
      const uint64_t kind = gen() % 10;
      weights[i] = kind == 0   ? 0.0
                   : kind == 1 ? -1.0
                   : kind == 2 ? std::nan("")
                               : static_cast<double>(gen() % 1000) / 7.0;
    }
    if (n == 1000) weights[3] = std::numeric_limits<double>::infinity();
    if (n >= 5) weights[n - 1] = weights[n - 2] = 0.0;
    WeightedSampler one_by_one;
    for (size_t i = 0; i < n; ++i) one_by_one.Set(i, weights[i]);
    WeightedSampler at_once;
    at_once.SetAll(weights);
    EXPECT_EQ(at_once.size(), one_by_one.size());
    for (int round = 0; round < 3; ++round) {
      std::mt19937_64 rng_a(round);
      std::mt19937_64 rng_b(round);
      EXPECT_EQ(at_once.Draw(n / 2 + 1, rng_a),
                one_by_one.Draw(n / 2 + 1, rng_b))
          << n;
      if (n > 0) {
        at_once.Set(round % n, 2.5);
        one_by_one.Set(round % n, 2.5);
        at_once.Clear((round + 1) % n);
        one_by_one.Clear((round + 1) % n);
      }
    }
  }
  // On a sampler that holds slots already: as Set for each.
  WeightedSampler used;
  used.Set(0, 1.0);
  used.SetAll(std::vector<double>{0.0, 3.0});
  EXPECT_EQ(used.size(), 2u);
}

}  // namespace
}  // namespace fleetmem::core
