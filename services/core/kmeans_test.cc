#include "services/core/kmeans.h"

#include <algorithm>
#include <limits>
#include <random>
#include <set>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

// `per_blob` points around each of `centres` (columns), Gaussian noise.
Eigen::MatrixXf Blobs(const Eigen::MatrixXf& centres, int per_blob, float noise,
                      uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> gauss(0.0f, noise);
  Eigen::MatrixXf points(centres.rows(), centres.cols() * per_blob);
  for (Eigen::Index b = 0; b < centres.cols(); ++b) {
    for (int i = 0; i < per_blob; ++i) {
      for (Eigen::Index d = 0; d < centres.rows(); ++d) {
        points(d, b * per_blob + i) = centres(d, b) + gauss(rng);
      }
    }
  }
  return points;
}

// Every cluster non-empty; each centroid is the mean of its points; the
// reported inertia matches.
void ExpectConsistent(const Eigen::MatrixXf& points, const KMeansResult& r,
                      int k) {
  ASSERT_EQ(r.assignment.size(), static_cast<size_t>(points.cols()));
  ASSERT_EQ(r.centroids.cols(), k);
  ASSERT_EQ(r.centroids.rows(), points.rows());
  std::vector<int> counts(k, 0);
  Eigen::MatrixXd sums = Eigen::MatrixXd::Zero(points.rows(), k);
  double inertia = 0.0;
  for (Eigen::Index i = 0; i < points.cols(); ++i) {
    const int c = r.assignment[i];
    ASSERT_GE(c, 0);
    ASSERT_LT(c, k);
    ++counts[c];
    sums.col(c) += points.col(i).cast<double>();
    inertia +=
        (points.col(i) - r.centroids.col(c)).cast<double>().squaredNorm();
  }
  for (int c = 0; c < k; ++c) {
    ASSERT_GT(counts[c], 0) << "cluster " << c << " is empty";
    const Eigen::VectorXd mean = sums.col(c) / counts[c];
    EXPECT_LT((mean - r.centroids.col(c).cast<double>()).norm(), 1e-4);
  }
  EXPECT_NEAR(r.inertia, inertia, 1e-3 * std::max(1.0, inertia));
}

// Lloyd has converged: every point's own centroid is (one of) its nearest.
void ExpectConverged(const Eigen::MatrixXf& points, const KMeansResult& r) {
  for (Eigen::Index i = 0; i < points.cols(); ++i) {
    const double own =
        (points.col(i) - r.centroids.col(r.assignment[i])).squaredNorm();
    const double nearest = (r.centroids.colwise() - points.col(i))
                               .colwise()
                               .squaredNorm()
                               .minCoeff();
    ASSERT_LE(own, nearest + 1e-5) << "point " << i;
  }
}

TEST(KMeansTest, SeparatesWellSeparatedBlobs) {
  Eigen::MatrixXf centres(2, 4);
  centres << 0, 20, 0, 20,  //
      0, 0, 20, 20;
  const Eigen::MatrixXf points = Blobs(centres, 25, 0.5f, 1);
  for (uint64_t seed = 0; seed < 10; ++seed) {
    std::mt19937_64 rng(seed);
    const KMeansResult r = KMeans(points, 4, 50, rng);
    ExpectConsistent(points, r, 4);
    std::set<int> labels;
    for (int b = 0; b < 4; ++b) {
      const int label = r.assignment[b * 25];
      labels.insert(label);
      for (int i = 0; i < 25; ++i) {
        ASSERT_EQ(r.assignment[b * 25 + i], label)
            << "seed " << seed << " blob " << b << " point " << i;
      }
    }
    EXPECT_EQ(labels.size(), 4u) << "seed " << seed;
    EXPECT_LT(r.inertia, 100 * 0.5 * 0.5 * 2 * 2);  // ~ noise variance only
    EXPECT_GE(r.iterations, 1);
  }
}

TEST(KMeansTest, ReproducibleForFixedSeed) {
  std::mt19937_64 data_rng(3);
  std::uniform_real_distribution<float> uniform(-1.0f, 1.0f);
  Eigen::MatrixXf points(16, 200);
  for (Eigen::Index i = 0; i < points.size(); ++i) {
    points.data()[i] = uniform(data_rng);
  }
  std::mt19937_64 rng_a(99), rng_b(99);
  const KMeansResult a = KMeans(points, 20, 50, rng_a);
  const KMeansResult b = KMeans(points, 20, 50, rng_b);
  EXPECT_EQ(a.assignment, b.assignment);
  EXPECT_TRUE(a.centroids == b.centroids);
  EXPECT_EQ(a.inertia, b.inertia);
  EXPECT_EQ(rng_a(), rng_b());  // same amount of randomness consumed
  ExpectConsistent(points, a, 20);
  ExpectConverged(points, a);
}

TEST(KMeansTest, KEqualsNumberOfPoints) {
  std::mt19937_64 data_rng(5);
  std::uniform_real_distribution<float> uniform(0.0f, 1.0f);
  Eigen::MatrixXf points(3, 12);
  for (Eigen::Index i = 0; i < points.size(); ++i) {
    points.data()[i] = uniform(data_rng);
  }
  std::mt19937_64 rng(1);
  const KMeansResult r = KMeans(points, 12, 50, rng);
  ExpectConsistent(points, r, 12);
  EXPECT_EQ(std::set<int>(r.assignment.begin(), r.assignment.end()).size(),
            12u);
  EXPECT_NEAR(r.inertia, 0.0, 1e-9);
}

TEST(KMeansTest, KEqualsNWithDuplicatePointsKeepsClustersNonEmpty) {
  Eigen::MatrixXf points(2, 6);
  points << 1, 1, 1, 5, 5, 5,  //
      0, 0, 0, 0, 0, 0;
  std::mt19937_64 rng(2);
  const KMeansResult r = KMeans(points, 6, 10, rng);
  ExpectConsistent(points, r, 6);
  EXPECT_NEAR(r.inertia, 0.0, 1e-9);
}

TEST(KMeansTest, AllPointsIdentical) {
  const Eigen::MatrixXf points = Eigen::MatrixXf::Constant(4, 10, 2.5f);
  std::mt19937_64 rng(2);
  const KMeansResult r = KMeans(points, 3, 10, rng);
  ExpectConsistent(points, r, 3);
}

// Points whose distances overflow (inf - inf = NaN) must still leave no
// cluster empty and no point unassigned (the upload fuzzer found an index of
// -1 here before places were bounded).
TEST(KMeansTest, NonFiniteDistancesStillFillEveryCluster) {
  const float inf = std::numeric_limits<float>::infinity();
  Eigen::MatrixXf points(1, 5);
  points << inf, inf, -inf, inf, -inf;
  std::mt19937_64 rng(3);
  const KMeansResult r = KMeans(points, 3, 5, rng);
  ASSERT_EQ(r.assignment.size(), 5u);
  std::vector<int> counts(3, 0);
  for (int a : r.assignment) {
    ASSERT_GE(a, 0);
    ASSERT_LT(a, 3);
    ++counts[a];
  }
  for (int count : counts) EXPECT_GE(count, 1);
}

TEST(KMeansTest, KLargerThanNIsClamped) {
  Eigen::MatrixXf points(1, 3);
  points << 0, 1, 2;
  std::mt19937_64 rng(2);
  const KMeansResult r = KMeans(points, 10, 10, rng);
  ExpectConsistent(points, r, 3);
}

TEST(KMeansTest, SingleClusterIsTheMean) {
  Eigen::MatrixXf points(2, 4);
  points << 0, 2, 0, 2,  //
      0, 0, 4, 4;
  std::mt19937_64 rng(2);
  const KMeansResult r = KMeans(points, 1, 10, rng);
  ExpectConsistent(points, r, 1);
  EXPECT_FLOAT_EQ(r.centroids(0, 0), 1.0f);
  EXPECT_FLOAT_EQ(r.centroids(1, 0), 2.0f);
  EXPECT_DOUBLE_EQ(r.inertia, 4 * 5.0);
}

TEST(KMeansTest, LloydImprovesOnSeeding) {
  std::mt19937_64 data_rng(11);
  std::uniform_real_distribution<float> uniform(0.0f, 1.0f);
  Eigen::MatrixXf points(2, 300);
  for (Eigen::Index i = 0; i < points.size(); ++i) {
    points.data()[i] = uniform(data_rng);
  }
  std::mt19937_64 rng_a(4), rng_b(4);
  const KMeansResult seeded = KMeans(points, 8, 0, rng_a);
  const KMeansResult refined = KMeans(points, 8, 100, rng_b);
  ExpectConsistent(points, seeded, 8);
  ExpectConsistent(points, refined, 8);
  ExpectConverged(points, refined);
  EXPECT_EQ(seeded.iterations, 0);
  EXPECT_LT(refined.inertia, seeded.inertia);
  EXPECT_LT(refined.iterations, 100);  // converged
}

}  // namespace
}  // namespace fleetmem::core
