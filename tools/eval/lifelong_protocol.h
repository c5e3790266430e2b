// The lifelong place-recognition protocol, version 2 (learning.md,
// "Evaluation protocol"; docs/results.md): the pure parts, unit-tested on
// hand-computed cases.
//
// A route of n places seen in two conditions (Nordland: summer, winter),
// place i of one condition aligned with place i of the other. The route is
// split into kAreas areas in route order; within each area every 4th place
// is held out: never trained on, in either condition. The map is the
// reference condition's frame of every place, held-out places included;
// the queries are the held-out places' frames of the other condition; a
// retrieved map entry is correct within +-tolerance route positions.
//
// Domains: reference areas 1..kAreas, then query-condition areas
// 1..kAreas. After each domain the queries of every area are scored.
#ifndef FLEETMEM_TOOLS_EVAL_LIFELONG_PROTOCOL_H_
#define FLEETMEM_TOOLS_EVAL_LIFELONG_PROTOCOL_H_

#include <cstddef>
#include <vector>

#include "Eigen/Dense"

namespace fleetmem::eval::lifelong {

inline constexpr int kAreas = 3;
inline constexpr int kDomains = 2 * kAreas;
inline constexpr int kMaxK = 6;
inline constexpr int kTolerance = 2;

struct Split {
  std::vector<int> area;       // per place, 0..kAreas-1
  std::vector<bool> held_out;  // per place
  // Places of `area` that are held out (queries) or trained on, in route
  // order.
  std::vector<size_t> Places(int area, bool held) const;
};

// Area of place i: floor(i * kAreas / n); held out: the 4th, 8th, ... place
// of its area (position within the area % 4 == 3).
Split SplitRoute(size_t n);

struct Score {
  double recall[kMaxK] = {};  // recall@1..6
  double wr = 0.0;            // 0.5 r1 + 0.1 (r2 + ... + r6)
};

// Rows of `rows` scaled to unit length (zero rows stay zero).
Eigen::MatrixXf UnitRows(const Eigen::MatrixXf& rows);

// Scores of the queries `places` (route positions), whose similarity to
// every map entry (map entry j = place j) is row r of `similarity`
// (|places| x n): ranked by similarity, ties by map position.
Score ScoreQueries(const Eigen::MatrixXf& similarity,
                   const std::vector<size_t>& places,
                   int tolerance = kTolerance);

// Every area's score: `map` and `queries` hold one unit descriptor row per
// place (n rows each); cosine similarity.
std::vector<Score> ScoreAreas(const Split& split, const Eigen::MatrixXf& map,
                              const Eigen::MatrixXf& queries,
                              int tolerance = kTolerance);

// SeqSLAM-style sequence matching (Milford and Wyeth 2012) over the
// single-frame similarities `frames` (n x n: query-condition place q
// against map place j): differences 1 - s, contrast-normalised within
// +-window map places of each row, summed along the diagonal over the
// query's last `length` places (the robot's own recent frames, held-out or
// not), with velocity 1: both conditions of this data are sampled at the
// same places. Returns a similarity (minus the mean normalised difference)
// of the same shape.
Eigen::MatrixXf SequenceSimilarity(const Eigen::MatrixXf& frames, int length,
                                   int window = 10);

// The expected score of a random ranking of an n-entry map: a query with m
// correct entries is found in the top k with probability
// 1 - C(n-m, k) / C(n, k).
Score ChanceScore(const Split& split, int tolerance = kTolerance);

// What a method reports: areas[t][a], area a's score after domain t.
struct Summary {
  double wr_final = 0;  // mean WR over the areas after the last domain
  // Mean over the query-condition domains of the WR on the area just
  // learned.
  double ae = 0;
  // Mean over the later query-condition domains of the mean WR on the
  // query-condition areas learned before them.
  double ra = 0;
  // Mean over the domains before the last of the mean WR on the areas whose
  // query-condition domain is still to come.
  double unseen = 0;
};
Summary Summarise(const std::vector<std::vector<Score>>& areas);

}  // namespace fleetmem::eval::lifelong

#endif  // FLEETMEM_TOOLS_EVAL_LIFELONG_PROTOCOL_H_
