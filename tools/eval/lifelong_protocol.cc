#include "tools/eval/lifelong_protocol.h"

#include <algorithm>
#include <cmath>
#include <numeric>

#include "services/core/place_metrics.h"

namespace fleetmem::eval::lifelong {

std::vector<size_t> Split::Places(int a, bool held) const {
  std::vector<size_t> out;
  for (size_t i = 0; i < area.size(); ++i) {
    if (area[i] == a && held_out[i] == held) out.push_back(i);
  }
  return out;
}

Split SplitRoute(size_t n) {
  Split split;
  size_t first_of_area = 0;
  for (size_t i = 0; i < n; ++i) {
    const int a = int(i * kAreas / n);
    if (i == 0 || a != split.area.back()) first_of_area = i;
    split.area.push_back(a);
    split.held_out.push_back((i - first_of_area) % 4 == 3);
  }
  return split;
}

Eigen::MatrixXf UnitRows(const Eigen::MatrixXf& rows) {
  Eigen::MatrixXf out = rows;
  for (Eigen::Index r = 0; r < out.rows(); ++r) {
    const float norm = out.row(r).norm();
    if (norm > 0) out.row(r) /= norm;
  }
  return out;
}

Score ScoreQueries(const Eigen::MatrixXf& similarity,
                   const std::vector<size_t>& places, int tolerance) {
  core::FirstCorrectRanks ranks;
  const Eigen::Index n = similarity.cols();
  std::vector<Eigen::Index> order(n);
  for (size_t r = 0; r < places.size(); ++r) {
    std::iota(order.begin(), order.end(), 0);
    const Eigen::Index k = std::min<Eigen::Index>(kMaxK, n);
    std::partial_sort(order.begin(), order.begin() + k, order.end(),
                      [&](Eigen::Index a, Eigen::Index b) {
                        const float sa = similarity(r, a),
                                    sb = similarity(r, b);
                        return sa > sb || (sa == sb && a < b);
                      });
    int first = 0;
    for (Eigen::Index j = 0; j < k && first == 0; ++j) {
      if (std::abs(long(order[j]) - long(places[r])) <= tolerance)
        first = int(j) + 1;
    }
    ranks.push_back(first);
  }
  Score score;
  for (int k = 1; k <= kMaxK; ++k)
    score.recall[k - 1] = core::RecallAtK(ranks, k);
  score.wr = core::WeightedRecall(ranks);
  return score;
}

std::vector<Score> ScoreAreas(const Split& split, const Eigen::MatrixXf& map,
                              const Eigen::MatrixXf& queries, int tolerance) {
  std::vector<Score> scores;
  for (int a = 0; a < kAreas; ++a) {
    const std::vector<size_t> places = split.Places(a, true);
    Eigen::MatrixXf q(places.size(), queries.cols());
    for (size_t r = 0; r < places.size(); ++r)
      q.row(r) = queries.row(places[r]);
    scores.push_back(ScoreQueries(q * map.transpose(), places, tolerance));
  }
  return scores;
}

Eigen::MatrixXf SequenceSimilarity(const Eigen::MatrixXf& frames, int length,
                                   int window) {
  const Eigen::Index n = frames.rows(), m = frames.cols();
  // Contrast-normalised differences, row by row.
  Eigen::MatrixXf normalised(n, m);
  for (Eigen::Index q = 0; q < n; ++q) {
    for (Eigen::Index j = 0; j < m; ++j) {
      const Eigen::Index lo = std::max<Eigen::Index>(0, j - window);
      const Eigen::Index hi = std::min<Eigen::Index>(m - 1, j + window);
      const Eigen::ArrayXf local =
          1.0f - frames.row(q).segment(lo, hi - lo + 1).array();
      const float mean = local.mean();
      const float sd = std::sqrt((local - mean).square().mean());
      normalised(q, j) = ((1.0f - frames(q, j)) - mean) / std::max(sd, 1e-6f);
    }
  }
  Eigen::MatrixXf out(n, m);
  for (Eigen::Index q = 0; q < n; ++q) {
    for (Eigen::Index j = 0; j < m; ++j) {
      float sum = 0;
      int count = 0;
      for (int l = 0; l < length && q - l >= 0 && j - l >= 0; ++l) {
        sum += normalised(q - l, j - l);
        ++count;
      }
      out(q, j) = -sum / float(std::max(count, 1));
    }
  }
  return out;
}

Score ChanceScore(const Split& split, int tolerance) {
  const long n = long(split.area.size());
  Score score;
  size_t queries = 0;
  for (long q = 0; q < n; ++q) {
    if (!split.held_out[q]) continue;
    ++queries;
    const long correct =
        std::min(n - 1, q + tolerance) - std::max(0L, q - tolerance) + 1;
    // P(no correct entry in the top k) = prod_{i<k} (n - correct - i) / (n -
    // i).
    double none = 1.0;
    for (int k = 1; k <= kMaxK; ++k) {
      const long i = k - 1;
      none *=
          (n - i > 0) ? std::max(0.0, double(n - correct - i) / (n - i)) : 0;
      score.recall[k - 1] += 1.0 - none;
    }
  }
  if (queries == 0) return score;
  for (double& r : score.recall) r /= double(queries);
  score.wr = 0.5 * score.recall[0];
  for (int k = 2; k <= kMaxK; ++k) score.wr += 0.1 * score.recall[k - 1];
  return score;
}

Summary Summarise(const std::vector<std::vector<Score>>& areas) {
  Summary s;
  if (areas.empty()) return s;
  for (const Score& a : areas.back()) s.wr_final += a.wr;
  s.wr_final /= double(areas.back().size());
  const int domains = int(areas.size());
  double ae = 0, ra = 0, unseen = 0;
  int ae_n = 0, ra_n = 0, unseen_n = 0;
  for (int t = 0; t < domains; ++t) {
    const int learned_query_areas = std::max(0, t - kAreas + 1);
    if (t >= kAreas) {
      ae += areas[t][t - kAreas].wr;
      ++ae_n;
      if (t - kAreas > 0) {
        double earlier = 0;
        for (int a = 0; a < t - kAreas; ++a) earlier += areas[t][a].wr;
        ra += earlier / (t - kAreas);
        ++ra_n;
      }
    }
    if (t + 1 < domains && learned_query_areas < kAreas) {
      double later = 0;
      for (int a = learned_query_areas; a < kAreas; ++a)
        later += areas[t][a].wr;
      unseen += later / (kAreas - learned_query_areas);
      ++unseen_n;
    }
  }
  s.ae = ae_n ? ae / ae_n : 0;
  s.ra = ra_n ? ra / ra_n : 0;
  s.unseen = unseen_n ? unseen / unseen_n : 0;
  return s;
}

}  // namespace fleetmem::eval::lifelong
