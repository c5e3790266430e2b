#include "clients/robot/learning/metric_head.h"

#include <cmath>
#include <random>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::robot::gpl {
namespace {

constexpr int kDim = 24;

// A route of `places` places 10 units apart seen in two domains. A place's
// code is its own random signature; the second domain adds a strong
// "season" direction of random strength, which swamps the signature under
// the raw cosine. Its strength is random per frame, or, with `smooth`,
// changes slowly along the route (neighbouring winter frames differ by
// little: winter frames alone do not show what the season changes).
std::vector<LearnSample> Route(int places, uint64_t seed, bool smooth = false) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> normal(0.0f, 1.0f);
  std::uniform_real_distribution<float> strength(4.0f, 12.0f);
  std::vector<std::vector<float>> signature(places, std::vector<float>(kDim));
  for (auto& s : signature)
    for (float& v : s) v = normal(rng);
  std::vector<LearnSample> out;
  for (int domain = 0; domain < 2; ++domain) {
    for (int i = 0; i < places; ++i) {
      LearnSample x;
      x.code = signature[i];
      for (float& v : x.code) v += 0.1f * normal(rng);
      if (domain == 1) {
        const float s =
            smooth ? 8.0f + 4.0f * std::sin(i / 8.0f) : strength(rng);
        for (int c = 0; c < 4; ++c) x.code[c] += s * (c % 2 ? -1.0f : 1.0f);
      }
      x.place.x = 10.0 * i;
      x.domain = domain;
      out.push_back(x);
    }
  }
  return out;
}

// Share of domain-1 samples whose nearest domain-0 descriptor (cosine) is
// their own place.
double RecallAtOne(MetricHead& head, const std::vector<LearnSample>& route,
                   int places) {
  std::vector<std::vector<float>> codes;
  for (const LearnSample& x : route) codes.push_back(x.code);
  auto d = head.Describe(codes);
  EXPECT_TRUE(d.ok()) << d.status();
  int correct = 0;
  for (int q = 0; q < places; ++q) {
    int best = -1;
    double best_sim = -2;
    for (int j = 0; j < places; ++j) {
      double sim = 0;
      for (size_t c = 0; c < (*d)[j].size(); ++c)
        sim += (*d)[places + q][c] * (*d)[j][c];
      if (sim > best_sim) best_sim = sim, best = j;
    }
    correct += best == q;
  }
  return double(correct) / places;
}

MetricHeadOptions Options() {
  MetricHeadOptions o;
  o.dimension = 16;
  o.pair_radius = 5.0;  // pairs are one place's two domains only
  return o;
}

TEST(MetricHeadTest, BeforeLearningTheDescriptorIsTheUnitCode) {
  MetricHead head(3, Options());
  auto d = head.Describe(std::vector<std::vector<float>>{{3, 0, 4}});
  ASSERT_TRUE(d.ok());
  EXPECT_THAT((*d)[0], testing::ElementsAre(0.6f, 0.0f, 0.8f));
  EXPECT_FALSE(head.fitted());
}

TEST(MetricHeadTest, CrossDomainPairsTeachWhatTheSeasonChanges) {
  const int places = 60;
  const auto train = Route(places, 1);
  const auto test = Route(places, 2);  // other places, same seasons
  MetricHead head(kDim, Options());
  const double raw = RecallAtOne(head, test, places);
  auto stats = head.Learn(train);
  ASSERT_TRUE(stats.ok()) << stats.status();
  EXPECT_EQ(stats->samples, 2u * places);
  EXPECT_EQ(stats->pairs, 2u * places);  // each sample with its partner
  EXPECT_EQ(stats->cross_domain_pairs, stats->pairs);
  const double learned = RecallAtOne(head, test, places);
  EXPECT_LT(raw, 0.5);
  EXPECT_GT(learned, 0.9) << "raw cosine " << raw;
  EXPECT_EQ(head.descriptor_dimension(), 16);
}

TEST(MetricHeadTest, WithoutTheOtherDomainItPairsWithinItsOwn) {
  const int places = 30;
  auto route = Route(places, 3);
  route.resize(places);  // domain 0 only
  MetricHeadOptions o = Options();
  o.pair_radius = 10.0;  // the neighbouring places
  o.max_partners = 4;
  MetricHead head(kDim, o);
  auto stats = head.Learn(route);
  ASSERT_TRUE(stats.ok());
  EXPECT_EQ(stats->cross_domain_pairs, 0u);
  EXPECT_EQ(stats->pairs, 2u * places - 2);  // ends have one neighbour
}

// What a Learn call is not given fades at the update rate: with rate 1 the
// head forgets the earlier samples entirely (it equals a head that saw only
// the last ones), with 0.5 it keeps part of them.
TEST(MetricHeadTest, TheUpdateRateBlendsEarlierStatisticsWithNewOnes) {
  const int places = 40;
  const auto both = Route(places, 4);
  const std::vector<LearnSample> winter(both.begin() + places, both.end());
  std::vector<std::vector<float>> codes;
  for (const LearnSample& x : both) codes.push_back(x.code);
  MetricHeadOptions o = Options();
  o.pair_radius = 10.0;
  auto descriptors_after = [&](double rate, bool first_both) {
    MetricHeadOptions with_rate = o;
    with_rate.update_rate = rate;
    MetricHead head(kDim, with_rate);
    if (first_both) EXPECT_TRUE(head.Learn(both).ok());
    EXPECT_TRUE(head.Learn(winter).ok());
    return *head.Describe(codes);
  };
  auto largest_gap = [](const std::vector<std::vector<float>>& a,
                        const std::vector<std::vector<float>>& b) {
    double gap = 0;
    for (size_t i = 0; i < a.size(); ++i)
      for (size_t c = 0; c < a[i].size(); ++c)
        gap = std::max(gap, double(std::abs(a[i][c] - b[i][c])));
    return gap;
  };
  const auto winter_only = descriptors_after(1.0, false);
  EXPECT_LT(largest_gap(descriptors_after(1.0, true), winter_only), 1e-4);
  EXPECT_GT(largest_gap(descriptors_after(0.5, true), winter_only), 0.1);
}

TEST(MetricHeadTest, ACodeOfTheWrongDimensionChangesNothing) {
  MetricHead head(kDim, Options());
  auto route = Route(10, 6);
  route[3].code.pop_back();
  auto stats = head.Learn(route);
  EXPECT_EQ(stats.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(head.fitted());
  EXPECT_EQ(
      head.Describe(std::vector<std::vector<float>>{{1.0f}}).status().code(),
      absl::StatusCode::kInvalidArgument);
}

TEST(MetricHeadTest, ExternalRewardIsTheHardestTripletsLoss) {
  // Three samples on a line of places; descriptors are the unit codes.
  MetricHeadOptions o;
  o.mining.positive_radius = 5;
  o.mining.negative_radius = 50;
  o.margin = 0.3f;
  MetricHead head(2, o);
  std::vector<LearnSample> segment{{{1, 0}, {0, 0, 0, 0}, 0}};
  std::vector<LearnSample> memory{{{0, 1}, {1, 0, 0, 0}, 1},        // positive
                                  {{1, 0.1f}, {100, 0, 0, 0}, 0}};  // negative
  auto r = head.ExternalRewards(segment, memory);
  ASSERT_TRUE(r.ok()) << r.status();
  // d(a,p)^2 = 2, d(a,n)^2 = |(1,0) - (1,0.1)/|(1,0.1)||^2.
  const double n = std::sqrt(1.01);
  const double dn = std::pow(1 - 1 / n, 2) + std::pow(0.1 / n, 2);
  EXPECT_NEAR((*r)[0], 2 + 0.3 - dn, 1e-5);
}

// A sample of weight 2 counts as the sample twice: the head fitted with
// the weight describes every code as the head fitted with a copy does (no
// pairs here, so the moments alone decide the fit).
TEST(MetricHeadTest, AWeightCountsAsCopies) {
  std::vector<LearnSample> route = Route(6, 11);
  MetricHeadOptions options;
  options.dimension = 4;
  options.pair_radius = -1;  // no pairs
  std::vector<LearnSample> weighted = route, copied = route;
  weighted[3].weight = 2.0;
  copied.push_back(route[3]);
  copied.back().place.x = 1e6;
  MetricHead a(kDim, options), b(kDim, options);
  ASSERT_TRUE(a.Learn(weighted).ok());
  ASSERT_TRUE(b.Learn(copied).ok());
  std::vector<std::vector<float>> codes;
  for (const LearnSample& x : route) codes.push_back(x.code);
  auto da = a.Describe(codes), db = b.Describe(codes);
  ASSERT_TRUE(da.ok() && db.ok());
  // An eigenvector's sign is arbitrary: compare the descriptors' cosines
  // with one another, which do not depend on it.
  auto cosine = [](const std::vector<float>& u, const std::vector<float>& v) {
    double dot = 0;
    for (size_t c = 0; c < u.size(); ++c) dot += double(u[c]) * v[c];
    return dot;
  };
  for (size_t i = 0; i < codes.size(); ++i) {
    for (size_t j = 0; j < codes.size(); ++j) {
      EXPECT_NEAR(cosine((*da)[i], (*da)[j]), cosine((*db)[i], (*db)[j]), 1e-6)
          << i << " " << j;
    }
  }
  // No weight at all is refused and changes nothing.
  for (LearnSample& x : weighted) x.weight = 0.0;
  MetricHead c(kDim, options);
  EXPECT_EQ(c.Learn(weighted).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(c.fitted());
}

}  // namespace
}  // namespace fleetmem::robot::gpl
