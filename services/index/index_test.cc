#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <Eigen/Core>
#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <filesystem>
#include <functional>
#include <iostream>
#include <limits>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/engine/place_index.h"
#include "services/index/exact_index.h"
#include "services/index/flann_index.h"
#include "services/index/float_file.h"
#include "services/index/hnsw_index.h"

namespace fleetmem::index {
namespace {

using engine::Neighbor;
using engine::PlaceIndex;
using engine::SearchParams;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;

using Vector = std::vector<float>;

// ---------------------------------------------------------------------------
// Data

Vector RandomGaussian(size_t dimension, std::mt19937& rng, float sigma = 1) {
  std::normal_distribution<float> normal(0.0f, sigma);
  Vector v(dimension);
  for (float& x : v) x = normal(rng);
  return v;
}

// Ids with gaussian vectors.
struct Dataset {
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
};
// Ids first..first+count-1 with gaussian vectors of `dimension`.
Dataset GaussianDataset(size_t count, size_t dimension, std::mt19937& rng,
                        uint64_t first = 0) {
  Dataset data;
  for (uint64_t id = first; id < first + count; ++id) {
    data.ids.push_back(id);
    data.vectors.push_back(RandomGaussian(dimension, rng));
  }
  return data;
}

Vector Normalized(Vector v) {
  double norm = 0;
  for (float x : v) norm += double{x} * x;
  norm = std::sqrt(norm);
  for (float& x : v) x = static_cast<float>(x / norm);
  return v;
}

Vector RandomUnit(size_t dimension, std::mt19937& rng) {
  return Normalized(RandomGaussian(dimension, rng));
}

// Unit vectors around `blobs` random unit centres: centre plus gaussian noise
// of expected norm `spread`, then normalised (places seen several times).
class BlobSource {
 public:
  BlobSource(size_t dimension, size_t blobs, float spread, std::mt19937& rng)
      : dimension_(dimension), spread_(spread) {
    for (size_t i = 0; i < blobs; ++i) {
      centres_.push_back(RandomUnit(dimension, rng));
    }
  }
  Vector Next(std::mt19937& rng) const {
    std::uniform_int_distribution<size_t> pick(0, centres_.size() - 1);
    Vector v = centres_[pick(rng)];
    const Vector noise = RandomGaussian(
        dimension_, rng, spread_ / std::sqrt(static_cast<float>(dimension_)));
    for (size_t i = 0; i < dimension_; ++i) v[i] += noise[i];
    return Normalized(std::move(v));
  }

 private:
  size_t dimension_;
  float spread_;
  std::vector<Vector> centres_;
};

// ---------------------------------------------------------------------------
// Naive reference: a map and a double-precision scan.

class NaiveIndex {
 public:
  void Add(const std::vector<uint64_t>& ids, const std::vector<Vector>& vs) {
    for (size_t i = 0; i < ids.size(); ++i) vectors_[ids[i]] = vs[i];
  }
  void Remove(const std::vector<uint64_t>& ids) {
    for (uint64_t id : ids) vectors_.erase(id);
  }
  // (squared distance in double, id), nearest first, ties by smaller id.
  std::vector<std::pair<double, uint64_t>> Search(
      const Vector& query, size_t k,
      const std::function<bool(uint64_t)>& accept = {}) const {
    std::vector<std::pair<double, uint64_t>> all;
    for (const auto& [id, v] : vectors_) {
      if (accept && !accept(id)) continue;
      double d = 0;
      for (size_t i = 0; i < v.size(); ++i) {
        const double diff = double{v[i]} - double{query[i]};
        d += diff * diff;
      }
      all.emplace_back(d, id);
    }
    std::sort(all.begin(), all.end());
    if (all.size() > k) all.resize(k);
    return all;
  }
  const std::map<uint64_t, Vector>& vectors() const { return vectors_; }

 private:
  std::map<uint64_t, Vector> vectors_;
};

std::vector<uint64_t> Ids(const std::vector<Neighbor>& neighbors) {
  std::vector<uint64_t> ids;
  for (const Neighbor& n : neighbors) ids.push_back(n.id);
  return ids;
}

std::vector<uint64_t> Ids(
    const std::vector<std::pair<double, uint64_t>>& reference) {
  std::vector<uint64_t> ids;
  for (const auto& [d, id] : reference) ids.push_back(id);
  return ids;
}

std::vector<Neighbor> SearchOk(const PlaceIndex& index, const Vector& query,
                               size_t k,
                               std::function<bool(uint64_t)> accept = {}) {
  SearchParams params;
  params.k = k;
  params.accept = std::move(accept);
  absl::StatusOr<std::vector<Neighbor>> result = index.Search(query, params);
  EXPECT_TRUE(result.ok()) << result.status();
  return result.ok() ? *std::move(result) : std::vector<Neighbor>();
}

// Expects `got` to be the reference answer: same ids in the same order and
// Euclidean distances within float rounding.
void ExpectSameAnswer(const std::vector<Neighbor>& got,
                      const std::vector<std::pair<double, uint64_t>>& want) {
  ASSERT_EQ(Ids(got), Ids(want));
  for (size_t i = 0; i < got.size(); ++i) {
    EXPECT_NEAR(got[i].distance, std::sqrt(want[i].first),
                1e-5 * (1 + std::sqrt(want[i].first)));
  }
}

// ---------------------------------------------------------------------------
// Implementations under test.

struct IndexCase {
  std::string name;
  std::function<std::unique_ptr<PlaceIndex>(size_t)> make;
  // Answers exactly (the exact index, or FLANN with unlimited checks).
  bool exact = true;
};

FlannIndexOptions FlannOptions(int checks, float removed_fraction,
                               float add_factor) {
  FlannIndexOptions options;
  options.checks = checks;
  options.rebuild_removed_fraction = removed_fraction;
  options.add_rebuild_factor = add_factor;
  return options;
}

std::vector<IndexCase> AllCases() {
  return {
      {"Exact", [](size_t d) { return NewExactIndex(d); }, true},
      {"FlannDefault", [](size_t d) { return NewFlannIndex(d); }, false},
      // Unlimited checks make FLANN exact, so its bookkeeping (point ids,
      // removals, rebuilds) can be compared with the reference.
      {"FlannUnlimitedChecks",
       [](size_t d) { return NewFlannIndex(d, FlannOptions(0, 0.25f, 2)); },
       true},
      // Rebuilds the trees on every Remove and almost every Add.
      {"FlannAlwaysRebuild",
       [](size_t d) { return NewFlannIndex(d, FlannOptions(0, 0, 1.01f)); },
       true},
      // Never rebuilds on Remove: removed points stay in FLANN's trees,
      // across FLANN's own rebuilds on growth.
      {"FlannNeverRebuildOnRemove",
       [](size_t d) { return NewFlannIndex(d, FlannOptions(0, 1e9f, 1.5f)); },
       true},
      // int8 codes (the default) and float codes.
      {"Hnsw", [](size_t d) { return NewHnswIndex(d); }, false},
      {"HnswFloat",
       [](size_t d) {
         HnswIndexOptions options;
         options.codes = HnswIndexOptions::Codes::kFloat;
         return NewHnswIndex(d, options);
       },
       false},
      // int8 codes whose floats are kept in a file (the server's default).
      {"HnswFloatsInAFile",
       [](size_t d) {
         HnswIndexOptions options;
         options.floats_dir = ::testing::TempDir();
         return NewHnswIndex(d, options);
       },
       false},
      // Switches exact -> HNSW at 8 vectors and back below 4, so the tests'
      // adds and removes cross the threshold both ways.
      {"TieredSwitching",
       [](size_t d) {
         TieredIndexOptions options;
         options.hnsw_from = 8;
         return NewTieredIndex(d, options);
       },
       false},
      // The same, the graph's floats in a file.
      {"TieredSwitchingFloatsInAFile",
       [](size_t d) {
         TieredIndexOptions options;
         options.hnsw_from = 8;
         options.hnsw.floats_dir = ::testing::TempDir();
         return NewTieredIndex(d, options);
       },
       false},
      // The same, with the graph filled by Add itself.
      {"TieredSynchronous",
       [](size_t d) {
         TieredIndexOptions options;
         options.hnsw_from = 8;
         options.background = false;
         return NewTieredIndex(d, options);
       },
       false},
  };
}

class PlaceIndexTest : public ::testing::TestWithParam<IndexCase> {
 protected:
  std::unique_ptr<PlaceIndex> Make(size_t dimension) {
    return GetParam().make(dimension);
  }
};

INSTANTIATE_TEST_SUITE_P(Implementations, PlaceIndexTest,
                         ::testing::ValuesIn(AllCases()),
                         [](const ::testing::TestParamInfo<IndexCase>& info) {
                           return info.param.name;
                         });

TEST_P(PlaceIndexTest, EmptyIndexFindsNothing) {
  std::unique_ptr<PlaceIndex> index = Make(4);
  EXPECT_EQ(index->size(), 0u);
  EXPECT_EQ(index->dimension(), 4u);
  EXPECT_THAT(SearchOk(*index, {1, 2, 3, 4}, 5), IsEmpty());
  ASSERT_TRUE(
      index->Add(std::vector<uint64_t>{7}, std::vector<Vector>{{1, 0, 0, 0}})
          .ok());
  EXPECT_THAT(SearchOk(*index, {1, 2, 3, 4}, 0), IsEmpty());
  ASSERT_TRUE(index->Remove(std::vector<uint64_t>{7}).ok());
  EXPECT_EQ(index->size(), 0u);
  EXPECT_THAT(SearchOk(*index, {1, 2, 3, 4}, 5), IsEmpty());
}

TEST_P(PlaceIndexTest, SmallExampleNearestFirstWithDistances) {
  std::unique_ptr<PlaceIndex> index = Make(2);
  ASSERT_TRUE(index
                  ->Add(std::vector<uint64_t>{1, 2, 3},
                        std::vector<Vector>{{0, 0}, {3, 4}, {1, 0}})
                  .ok());
  EXPECT_EQ(index->size(), 3u);
  std::vector<Neighbor> got = SearchOk(*index, {0, 0}, 5);
  ASSERT_THAT(Ids(got), ElementsAre(1, 3, 2));
  EXPECT_FLOAT_EQ(got[0].distance, 0.0f);
  EXPECT_FLOAT_EQ(got[1].distance, 1.0f);
  EXPECT_FLOAT_EQ(got[2].distance, 5.0f);
}

TEST_P(PlaceIndexTest, EqualDistancesGoToTheSmallerIdFirst) {
  std::unique_ptr<PlaceIndex> index = Make(3);
  ASSERT_TRUE(
      index
          ->Add(std::vector<uint64_t>{30, 10, 20, 5},
                std::vector<Vector>{{1, 1, 1}, {1, 1, 1}, {1, 1, 1}, {9, 9, 9}})
          .ok());
  EXPECT_THAT(Ids(SearchOk(*index, {1, 1, 1}, 3)), ElementsAre(10, 20, 30));
  EXPECT_THAT(Ids(SearchOk(*index, {1, 1, 1}, 4)), ElementsAre(10, 20, 30, 5));
}

TEST_P(PlaceIndexTest, WrongQueryDimensionIsInvalidArgument) {
  std::unique_ptr<PlaceIndex> index = Make(3);
  ASSERT_TRUE(
      index->Add(std::vector<uint64_t>{1}, std::vector<Vector>{{1, 2, 3}})
          .ok());
  SearchParams params;
  params.k = 1;
  for (const Vector& query : {Vector{1, 2}, Vector{1, 2, 3, 4}, Vector{}}) {
    absl::StatusOr<std::vector<Neighbor>> result = index->Search(query, params);
    EXPECT_EQ(result.status().code(), absl::StatusCode::kInvalidArgument)
        << query.size();
    EXPECT_THAT(result.status().message(), HasSubstr("dimension"));
  }
  absl::StatusOr<std::vector<Neighbor>> nan =
      index->Search(Vector{1, NAN, 3}, params);
  EXPECT_EQ(nan.status().code(), absl::StatusCode::kInvalidArgument);
}

struct BadAdd {
  std::string what;
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
  std::string message;  // part of the error message
};

TEST_P(PlaceIndexTest, BadAddIsInvalidArgumentAndAddsNothing) {
  const std::vector<BadAdd> cases = {
      {"wrong dimension in the middle",
       {10, 11, 12},
       {{1, 1, 1}, {2, 2}, {3, 3, 3}},
       "dimension 2"},
      {"used id", {10, 2, 12}, {{1, 1, 1}, {2, 2, 2}, {3, 3, 3}}, "id 2"},
      {"id twice in the batch",
       {10, 11, 10},
       {{1, 1, 1}, {2, 2, 2}, {3, 3, 3}},
       "twice"},
      {"more ids than vectors", {10, 11}, {{1, 1, 1}}, "2 ids but 1 vectors"},
      {"non-finite value",
       {10, 11},
       {{1, 1, 1}, {2, INFINITY, 2}},
       "non-finite"},
  };
  for (const BadAdd& bad : cases) {
    SCOPED_TRACE(bad.what);
    std::unique_ptr<PlaceIndex> index = Make(3);
    ASSERT_TRUE(index
                    ->Add(std::vector<uint64_t>{1, 2},
                          std::vector<Vector>{{0, 0, 0}, {5, 5, 5}})
                    .ok());
    absl::Status status = index->Add(bad.ids, bad.vectors);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(status.message(), HasSubstr(bad.message));
    EXPECT_EQ(index->size(), 2u);
    // Only the two original vectors are found, even next to the bad batch's.
    EXPECT_THAT(Ids(SearchOk(*index, {1, 1, 1}, 10)), ElementsAre(1, 2));
    // The batch's ids are free: the corrected batch goes in.
    ASSERT_TRUE(index
                    ->Add(std::vector<uint64_t>{10, 11, 12},
                          std::vector<Vector>{{1, 1, 1}, {2, 2, 2}, {3, 3, 3}})
                    .ok());
    EXPECT_EQ(index->size(), 5u);
  }
}

std::vector<std::span<const float>> Views(const std::vector<Vector>& vectors) {
  return std::vector<std::span<const float>>(vectors.begin(), vectors.end());
}

TEST_P(PlaceIndexTest, AddNormalizedStoresWhatAddOfNormalizedCopiesStores) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(11);
  auto [ids, codes] = GaussianDataset(300, kDimension, rng);
  codes[5] = Vector(kDimension, 0.0f);  // a zero code stays zero
  std::vector<Vector> normalized;
  for (const Vector& code : codes) {
    normalized.push_back(core::NormalizedCode(code));
  }
  std::unique_ptr<PlaceIndex> copied = Make(kDimension);
  std::unique_ptr<PlaceIndex> scaled = Make(kDimension);
  ASSERT_TRUE(copied->Add(ids, normalized).ok());
  ASSERT_TRUE(scaled->AddNormalized(ids, Views(codes)).ok());
  ASSERT_EQ(scaled->size(), copied->size());
  for (size_t i = 0; i < codes.size(); i += 7) {
    // The stored vectors are the normalised codes: every distance is the
    // one between normalised codes.
    const std::vector<Neighbor> got = SearchOk(*scaled, normalized[i], 5);
    ASSERT_FALSE(got.empty());
    for (const Neighbor& n : got) {
      const Eigen::Map<const Eigen::VectorXf> a(normalized[i].data(),
                                                kDimension);
      const Eigen::Map<const Eigen::VectorXf> b(normalized[n.id].data(),
                                                kDimension);
      EXPECT_NEAR(n.distance, (a - b).norm(), 1e-4) << i << " " << n.id;
    }
    // An exact index answers as if given the copies: the same neighbours,
    // at distances within float rounding (the exact index keeps the codes
    // as given with their scales, so its distances are to the exactly
    // scaled code rather than to the rounded copy).
    if (GetParam().exact) {
      const std::vector<Neighbor> want = SearchOk(*copied, normalized[i], 5);
      ASSERT_EQ(Ids(got), Ids(want)) << i;
      for (size_t j = 0; j < got.size(); ++j) {
        EXPECT_NEAR(got[j].distance, want[j].distance, 1e-6) << i;
      }
    }
  }
  // The checks are Add's: a bad batch adds nothing.
  const std::vector<Vector> bad = {{1.0f}, Vector(kDimension, NAN)};
  for (const Vector& code : bad) {
    absl::Status status = scaled->AddNormalized(
        std::vector<uint64_t>{1000}, Views(std::vector<Vector>{code}));
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  }
  EXPECT_EQ(scaled
                ->AddNormalized(std::vector<uint64_t>{1000, ids[0]},
                                Views({codes[0], codes[1]}))
                .code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(scaled->size(), copied->size());
}

TEST_P(PlaceIndexTest, ZeroDimensionIndexRefusesVectors) {
  std::unique_ptr<PlaceIndex> index = Make(0);
  EXPECT_EQ(
      index->Add(std::vector<uint64_t>{1}, std::vector<Vector>{{}}).code(),
      absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(index->size(), 0u);
}

TEST_P(PlaceIndexTest, RemoveIgnoresUnknownIds) {
  std::unique_ptr<PlaceIndex> index = Make(2);
  ASSERT_TRUE(index
                  ->Add(std::vector<uint64_t>{1, 2},
                        std::vector<Vector>{{0, 0}, {1, 1}})
                  .ok());
  EXPECT_TRUE(index->Remove(std::vector<uint64_t>{99, 2, 2, 100}).ok());
  EXPECT_EQ(index->size(), 1u);
  EXPECT_THAT(Ids(SearchOk(*index, {1, 1}, 5)), ElementsAre(1));
}

TEST_P(PlaceIndexTest, AgreesWithNaiveReferenceThroughAddsAndRemoves) {
  if (!GetParam().exact) GTEST_SKIP() << "approximate: see the recall test";
  constexpr size_t kDimension = 16;
  std::mt19937 rng(42);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  NaiveIndex reference;
  uint64_t next_id = 1000;
  std::uniform_int_distribution<int> batch_size(1, 40);
  for (int round = 0; round < 60; ++round) {
    SCOPED_TRACE(round);
    // Add a batch with ids out of order.
    std::vector<uint64_t> ids;
    std::vector<Vector> vectors;
    const int n = batch_size(rng);
    for (int i = 0; i < n; ++i) {
      ids.push_back(next_id + static_cast<uint64_t>(n - i) * 7919 % 100003);
      vectors.push_back(RandomGaussian(kDimension, rng));
    }
    next_id += 100003;
    ASSERT_TRUE(index->Add(ids, vectors).ok());
    reference.Add(ids, vectors);
    // Remove a random share of what is stored, plus an unknown id.
    std::vector<uint64_t> removed = {1};
    std::bernoulli_distribution remove(round % 3 == 0 ? 0.5 : 0.15);
    for (const auto& [id, v] : reference.vectors()) {
      if (remove(rng)) removed.push_back(id);
    }
    ASSERT_TRUE(index->Remove(removed).ok());
    reference.Remove(removed);
    ASSERT_EQ(index->size(), reference.vectors().size());
    for (int q = 0; q < 5; ++q) {
      const Vector query = RandomGaussian(kDimension, rng);
      for (size_t k : {1, 5, 30}) {
        ExpectSameAnswer(SearchOk(*index, query, k),
                         reference.Search(query, k));
      }
    }
  }
}

TEST_P(PlaceIndexTest, RemovedIdsNeverComeBack) {
  constexpr size_t kDimension = 8;
  std::mt19937 rng(7);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  auto [ids, vectors] = GaussianDataset(400, kDimension, rng);
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  std::set<uint64_t> removed;
  for (int step = 0; step < 10; ++step) {
    std::vector<uint64_t> batch;
    for (uint64_t id = step; id < 400; id += 13) batch.push_back(id);
    ASSERT_TRUE(index->Remove(batch).ok());
    removed.insert(batch.begin(), batch.end());
    // New vectors equal to removed ones, under new ids.
    std::vector<uint64_t> new_ids;
    std::vector<Vector> new_vectors;
    for (size_t i = 0; i < 3; ++i) {
      new_ids.push_back(1000 + step * 10 + i);
      new_vectors.push_back(vectors[batch[i]]);
    }
    ASSERT_TRUE(index->Add(new_ids, new_vectors).ok());
    ASSERT_EQ(index->size(), 400 - removed.size() + 3 * (step + 1));
    // Ask for everything, and for the removed vectors themselves.
    for (const Neighbor& n : SearchOk(*index, vectors[batch[0]], 1000)) {
      EXPECT_FALSE(removed.contains(n.id)) << n.id;
    }
    EXPECT_EQ(SearchOk(*index, vectors[0], 1000).size(), index->size());
    for (uint64_t id : batch) {
      for (const Neighbor& n : SearchOk(*index, vectors[id], 3)) {
        EXPECT_FALSE(removed.contains(n.id)) << n.id;
      }
    }
  }
}

TEST_P(PlaceIndexTest, AcceptFilterOnlyReturnsAcceptedIds) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(3);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  NaiveIndex reference;
  auto [ids, vectors] = GaussianDataset(600, kDimension, rng);
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  reference.Add(ids, vectors);
  struct Filter {
    std::string what;
    std::function<bool(uint64_t)> accept;
    size_t accepted;
  };
  const std::vector<Filter> filters = {
      {"even", [](uint64_t id) { return id % 2 == 0; }, 300},
      {"one in 97", [](uint64_t id) { return id % 97 == 5; }, 7},
      {"one id", [](uint64_t id) { return id == 321; }, 1},
      {"none", [](uint64_t) { return false; }, 0},
  };
  for (const Filter& filter : filters) {
    SCOPED_TRACE(filter.what);
    for (int q = 0; q < 10; ++q) {
      const Vector query = RandomGaussian(kDimension, rng);
      const std::vector<Neighbor> got =
          SearchOk(*index, query, 10, filter.accept);
      // Never an id the filter refuses, and as many as there are (<= k).
      EXPECT_EQ(got.size(), std::min<size_t>(10, filter.accepted));
      for (const Neighbor& n : got) EXPECT_TRUE(filter.accept(n.id)) << n.id;
      if (GetParam().exact) {
        ExpectSameAnswer(got, reference.Search(query, 10, filter.accept));
      }
    }
  }
}

TEST_P(PlaceIndexTest, StoredVectorFindsItselfFirst) {
  constexpr size_t kDimension = 256;
  std::mt19937 rng(11);
  BlobSource blobs(kDimension, 50, 0.6f, rng);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
  for (uint64_t id = 0; id < 2000; ++id) {
    ids.push_back(id * 3 + 1);
    vectors.push_back(blobs.Next(rng));
  }
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  size_t found_first = 0;
  for (size_t i = 0; i < ids.size(); ++i) {
    const std::vector<Neighbor> got = SearchOk(*index, vectors[i], 2);
    ASSERT_EQ(got.size(), 2u);
    if (got[0].id == ids[i]) {
      ++found_first;
      EXPECT_EQ(got[0].distance, 0.0f);
    }
  }
  if (GetParam().exact) {
    EXPECT_EQ(found_first, ids.size());
  } else {
    std::cout << "[ measured ] " << GetParam().name
              << " stored vector found first: " << found_first << " / "
              << ids.size() << "\n";
    EXPECT_GE(found_first, ids.size() * 99 / 100);
  }
}

// The bytes of index.Save, or its status.
absl::StatusOr<std::string> Saved(const PlaceIndex& index) {
  std::string bytes;
  core::ByteWriter out([&bytes](std::span<const char> data) {
    bytes.append(data.data(), data.size());
  });
  absl::Status status = index.Save(out);
  if (!status.ok()) return status;
  return bytes;
}

absl::Status LoadFrom(PlaceIndex& index, std::string_view bytes) {
  core::ByteReader in(bytes);
  absl::Status status = index.Load(in);
  if (status.ok() && in.remaining() != 0) {
    return absl::DataLossError("bytes left over");
  }
  return status;
}

// Both indexes give the same (id, distance) lists for `queries`.
void ExpectSameAnswers(const PlaceIndex& a, const PlaceIndex& b,
                       const std::vector<Vector>& queries) {
  for (const Vector& query : queries) {
    const std::vector<Neighbor> from_a = SearchOk(a, query, 10);
    const std::vector<Neighbor> from_b = SearchOk(b, query, 10);
    ASSERT_EQ(from_a.size(), from_b.size());
    for (size_t i = 0; i < from_a.size(); ++i) {
      EXPECT_EQ(from_a[i].id, from_b[i].id);
      EXPECT_EQ(from_a[i].distance, from_b[i].distance);
    }
  }
}

// A loaded index answers as the saved one did, and the same later calls
// keep both the same (an HNSW graph's level generator and free slots are
// saved too).
TEST_P(PlaceIndexTest, SavedIndexLoadsToTheSameAnswers) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(17);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  Dataset data = GaussianDataset(600, kDimension, rng);
  ASSERT_TRUE(index->Add(data.ids, data.vectors).ok());
  std::vector<uint64_t> removed;
  for (uint64_t id = 0; id < 600; id += 7) removed.push_back(id);
  ASSERT_TRUE(index->Remove(removed).ok());
  Dataset more = GaussianDataset(50, kDimension, rng, 1000);
  ASSERT_TRUE(index->Add(more.ids, more.vectors).ok());
  WaitForIndexing(*index);
  absl::StatusOr<std::string> bytes = Saved(*index);
  if (absl::IsUnimplemented(bytes.status())) {
    // FLANN's trees are not saved (a restart rebuilds them); no other index
    // may say so.
    EXPECT_THAT(GetParam().name, HasSubstr("Flann"));
    return;
  }
  ASSERT_TRUE(bytes.ok()) << bytes.status();

  std::unique_ptr<PlaceIndex> loaded = Make(kDimension);
  ASSERT_TRUE(LoadFrom(*loaded, *bytes).ok());
  EXPECT_EQ(loaded->size(), index->size());
  std::vector<Vector> queries;
  for (int i = 0; i < 50; ++i) {
    queries.push_back(RandomGaussian(kDimension, rng));
  }
  ExpectSameAnswers(*index, *loaded, queries);

  Dataset later = GaussianDataset(40, kDimension, rng, 2000);
  const std::vector<uint64_t> removed_later = {1, 2, 3, 1000, 1001};
  for (PlaceIndex* each : {index.get(), loaded.get()}) {
    ASSERT_TRUE(each->Remove(removed_later).ok());
    ASSERT_TRUE(each->Add(later.ids, later.vectors).ok());
    WaitForIndexing(*each);
  }
  ExpectSameAnswers(*index, *loaded, queries);

  // Into a used index, with another dimension, or from cut bytes: an
  // error, never a crash.
  EXPECT_FALSE(LoadFrom(*loaded, *bytes).ok());
  EXPECT_FALSE(LoadFrom(*Make(kDimension + 1), *bytes).ok());
  for (size_t cut :
       {size_t{0}, size_t{3}, bytes->size() / 2, bytes->size() - 1}) {
    EXPECT_FALSE(LoadFrom(*Make(kDimension), bytes->substr(0, cut)).ok())
        << "cut at " << cut;
  }
}

// A unit query compares the code as AddNormalized's codes are compared: a
// code finds its stored copy first, at distance exactly 0, and the other
// distances are those between the normalised codes.
TEST_P(PlaceIndexTest, UnitQueryFindsItsCodeAtDistanceZero) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(29);
  auto [ids, codes] = GaussianDataset(200, kDimension, rng);
  for (size_t i = 0; i < codes.size(); ++i) {
    for (float& x : codes[i]) x *= 0.1f + static_cast<float>(i % 7);
  }
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  ASSERT_TRUE(index->AddNormalized(ids, Views(codes)).ok());
  WaitForIndexing(*index);
  for (size_t i = 0; i < codes.size(); i += 9) {
    SearchParams params;
    params.k = 3;
    params.unit_query = true;
    absl::StatusOr<std::vector<Neighbor>> got = index->Search(codes[i], params);
    ASSERT_TRUE(got.ok()) << got.status();
    ASSERT_FALSE(got->empty());
    EXPECT_EQ(got->front().id, ids[i]);
    EXPECT_EQ(got->front().distance, 0.0f) << i;
    for (const Neighbor& n : *got) {
      EXPECT_NEAR(
          n.distance,
          core::CodeDistance(codes[i], codes[static_cast<size_t>(n.id)]), 1e-5)
          << i << " " << n.id;
    }
  }
}

// HoldsCode's promise, for every kind: a held code comes back bit for bit
// as it was given (AddNormalized's before scaling, Add's as is) and stays
// held until removed, through adds and removes that cross a tiered index's
// thresholds both ways, and through Save and Load. The exact, HNSW and
// tiered indexes hold every code; FLANN holds none.
TEST_P(PlaceIndexTest, HeldCodesComeBackAsGivenUntilRemoved) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(23);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  std::map<uint64_t, Vector> given;
  std::set<uint64_t> held;
  uint64_t next_id = 0;
  auto add = [&](size_t count, bool normalize) {
    Dataset data = GaussianDataset(count, kDimension, rng, next_id);
    next_id += count;
    for (Vector& v : data.vectors) {
      for (float& x : v) x *= 3.5f;  // far from unit length
    }
    ASSERT_TRUE((normalize ? index->AddNormalized(data.ids, Views(data.vectors))
                           : index->Add(data.ids, data.vectors))
                    .ok());
    for (size_t i = 0; i < count; ++i) given[data.ids[i]] = data.vectors[i];
  };
  auto remove_all_but = [&](size_t keep) {
    std::vector<uint64_t> ids;
    for (const auto& [id, v] : given) {
      if (given.size() - ids.size() > keep) ids.push_back(id);
    }
    ASSERT_TRUE(index->Remove(ids).ok());
    for (uint64_t id : ids) {
      given.erase(id);
      held.erase(id);
      EXPECT_FALSE(index->HoldsCode(id)) << id;
      Vector none = {7.0f};
      EXPECT_FALSE(index->CopyCode(id, &none)) << id;
      EXPECT_EQ(none, Vector{7.0f});
    }
  };
  auto check = [&](const std::string& step) {
    WaitForIndexing(*index);
    for (const auto& [id, v] : given) {
      const bool holds = index->HoldsCode(id);
      EXPECT_TRUE(holds || !held.contains(id)) << step << ": " << id;
      Vector copy;
      EXPECT_EQ(index->CopyCode(id, &copy), holds) << step << ": " << id;
      if (!holds) continue;
      held.insert(id);
      ASSERT_EQ(copy.size(), v.size());
      EXPECT_EQ(std::memcmp(copy.data(), v.data(), v.size() * sizeof(float)), 0)
          << step << ": " << id;
    }
  };
  add(6, true);
  add(3, false);
  check("above the switch");
  remove_all_but(3);
  check("below half of it");
  add(10, true);
  check("above it again");
  absl::StatusOr<std::string> bytes = Saved(*index);
  if (bytes.ok()) {
    index = Make(kDimension);
    ASSERT_TRUE(LoadFrom(*index, *bytes).ok());
    check("loaded");
  }
  if (GetParam().name.starts_with("Flann")) {
    EXPECT_TRUE(held.empty());  // FLANN keeps normalised copies
  } else {
    EXPECT_EQ(held.size(), given.size());
  }
}

TEST_P(PlaceIndexTest, ConcurrentSearchesGiveTheSequentialAnswers) {
  constexpr size_t kDimension = 32;
  std::mt19937 rng(13);
  std::unique_ptr<PlaceIndex> index = Make(kDimension);
  auto [ids, vectors] = GaussianDataset(1000, kDimension, rng);
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  ASSERT_TRUE(index->Remove(std::vector<uint64_t>{1, 2, 3, 500}).ok());
  std::vector<Vector> queries;
  std::vector<std::vector<uint64_t>> sequential;
  for (int q = 0; q < 50; ++q) {
    queries.push_back(RandomGaussian(kDimension, rng));
    sequential.push_back(Ids(SearchOk(*index, queries.back(), 7)));
  }
  std::vector<std::vector<std::vector<uint64_t>>> answers(4);
  std::vector<std::thread> threads;
  for (size_t t = 0; t < answers.size(); ++t) {
    threads.emplace_back([&, t] {
      for (int round = 0; round < 5; ++round) {
        for (const Vector& query : queries) {
          answers[t].push_back(Ids(SearchOk(*index, query, 7)));
        }
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  for (const auto& answer : answers) {
    ASSERT_EQ(answer.size(), 5 * queries.size());
    for (size_t i = 0; i < answer.size(); ++i) {
      EXPECT_EQ(answer[i], sequential[i % queries.size()]);
    }
  }
}

// ---------------------------------------------------------------------------
// The exact index against a double-precision scan.

TEST(ExactIndexTest, AnswersAfterMostIsRemovedAndGrowsAgain) {
  constexpr size_t kDimension = 8;
  std::mt19937 rng(5);
  std::unique_ptr<PlaceIndex> index = NewExactIndex(kDimension);
  auto [ids, vectors] = GaussianDataset(5000, kDimension, rng);
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  // Remove from the end in small steps, as a tiered index's indexer does,
  // down to 100 vectors; the storage shrinks on the way.
  for (size_t end = 5000; end > 100; end -= 4) {
    std::vector<uint64_t> batch(ids.begin() + end - 4, ids.begin() + end);
    ASSERT_TRUE(index->Remove(batch).ok());
  }
  ASSERT_EQ(index->size(), 100u);
  for (size_t i = 0; i < 100; i += 9) {
    EXPECT_EQ(SearchOk(*index, vectors[i], 1).front().id, ids[i]);
  }
  // It grows again.
  std::vector<uint64_t> more_ids;
  for (size_t i = 100; i < 3000; ++i) more_ids.push_back(ids[i]);
  ASSERT_TRUE(index
                  ->Add(more_ids, std::vector<Vector>(vectors.begin() + 100,
                                                      vectors.begin() + 3000))
                  .ok());
  EXPECT_EQ(index->size(), 3000u);
  EXPECT_EQ(SearchOk(*index, vectors[2999], 1).front().id, ids[2999]);
}

TEST(ExactIndexTest, MatchesDoublePrecisionScanAfterManyRemoves) {
  constexpr size_t kDimension = 64;
  std::mt19937 rng(5);
  std::unique_ptr<PlaceIndex> index = NewExactIndex(kDimension);
  NaiveIndex reference;
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
  std::uniform_real_distribution<float> scale(0.1f, 10.0f);
  for (uint64_t id = 0; id < 3000; ++id) {
    ids.push_back(id);
    Vector v = RandomGaussian(kDimension, rng);
    const float s = scale(rng);  // norms far apart
    for (float& x : v) x *= s;
    vectors.push_back(std::move(v));
  }
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  reference.Add(ids, vectors);
  std::vector<uint64_t> order = ids;
  std::shuffle(order.begin(), order.end(), rng);
  for (size_t start = 0; start < 2500; start += 250) {
    std::vector<uint64_t> batch(order.begin() + start,
                                order.begin() + start + 250);
    ASSERT_TRUE(index->Remove(batch).ok());
    reference.Remove(batch);
    for (int q = 0; q < 10; ++q) {
      Vector query = RandomGaussian(kDimension, rng);
      for (float& x : query) x *= scale(rng);
      ExpectSameAnswer(SearchOk(*index, query, 10),
                       reference.Search(query, 10));
    }
  }
  EXPECT_EQ(index->size(), 500u);
}

// The streaming scan takes 16, then 4 values at a time and finishes with
// single ones: every dimension's tail must count, on both scans.
TEST(ExactIndexTest, BothScansMatchDoublePrecisionAtEveryTailLength) {
  std::mt19937 rng(11);
  for (size_t streaming_scan_bytes : {size_t{0}, SIZE_MAX}) {
    for (size_t dimension : {1u, 3u, 4u, 7u, 17u, 30u, 259u}) {
      SCOPED_TRACE(testing::Message()
                   << "dimension " << dimension << ", streaming from "
                   << streaming_scan_bytes << " bytes");
      std::unique_ptr<PlaceIndex> index = NewExactIndex(
          dimension, {.streaming_scan_bytes = streaming_scan_bytes});
      NaiveIndex reference;
      std::vector<uint64_t> ids;
      std::vector<Vector> vectors;
      for (uint64_t id = 0; id < 700; ++id) {
        ids.push_back(id);
        vectors.push_back(RandomGaussian(dimension, rng));
      }
      ASSERT_TRUE(index->Add(ids, vectors).ok());
      reference.Add(ids, vectors);
      for (int q = 0; q < 10; ++q) {
        const Vector query = RandomGaussian(dimension, rng);
        ExpectSameAnswer(SearchOk(*index, query, 10),
                         reference.Search(query, 10));
      }
    }
  }
}

// Near-duplicates differ by less than the rounding error of
// ‖x‖² − 2xᵀq + ‖q‖² in float; the order must still be the exact one.
TEST(ExactIndexTest, OrdersNearDuplicatesExactly) {
  constexpr size_t kDimension = 256;
  std::mt19937 rng(9);
  std::unique_ptr<PlaceIndex> index = NewExactIndex(kDimension);
  NaiveIndex reference;
  const Vector base = RandomUnit(kDimension, rng);
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
  for (uint64_t id = 0; id < 500; ++id) {
    Vector v = base;
    const Vector noise = RandomGaussian(kDimension, rng, 1e-4f);
    for (size_t i = 0; i < kDimension; ++i) v[i] += noise[i];
    ids.push_back(id);
    vectors.push_back(std::move(v));
  }
  for (uint64_t id = 500; id < 1500; ++id) {
    ids.push_back(id);
    vectors.push_back(RandomUnit(kDimension, rng));
  }
  ASSERT_TRUE(index->Add(ids, vectors).ok());
  reference.Add(ids, vectors);
  for (int q = 0; q < 20; ++q) {
    Vector query = base;
    const Vector noise = RandomGaussian(kDimension, rng, 1e-4f);
    for (size_t i = 0; i < kDimension; ++i) query[i] += noise[i];
    ExpectSameAnswer(SearchOk(*index, query, 10), reference.Search(query, 10));
    // A stored near-duplicate finds itself at distance 0, not at the
    // rounding error of the expansion (~1e-3 after the square root).
    const std::vector<Neighbor> self = SearchOk(*index, vectors[q], 1);
    ASSERT_EQ(self.size(), 1u);
    EXPECT_EQ(self[0].id, ids[q]);
    EXPECT_EQ(self[0].distance, 0.0f);
  }
}

// ---------------------------------------------------------------------------
// FLANN recall against the exact index on 256-d unit vectors.

struct Recall {
  double at1 = 0;
  double at10 = 0;
};

// Mean over queries of |approximate top-k ∩ exact top-k| / k.
Recall MeasureRecall(const PlaceIndex& approximate, const PlaceIndex& exact,
                     const std::vector<Vector>& queries) {
  Recall recall;
  for (const Vector& query : queries) {
    const std::vector<Neighbor> truth = SearchOk(exact, query, 10);
    const std::vector<Neighbor> got = SearchOk(approximate, query, 10);
    EXPECT_EQ(got.size(), 10u);
    std::set<uint64_t> true_ids;
    for (const Neighbor& n : truth) true_ids.insert(n.id);
    size_t hits = 0;
    for (const Neighbor& n : got) hits += true_ids.contains(n.id);
    recall.at10 += hits / 10.0;
    recall.at1 += !got.empty() && got[0].id == truth[0].id;
  }
  recall.at1 /= queries.size();
  recall.at10 /= queries.size();
  return recall;
}

struct RecallCase {
  std::string data;
  std::function<Vector(std::mt19937&)> next;
  // Floors a little below the lowest recall of 20 runs (FLANN builds its
  // trees from std::random_device, so runs differ). Measured over 20 runs:
  // blobs recall@1 0.850-0.927 (mean 0.892), recall@10 0.851-0.877 (0.863);
  // uniform recall@1 0.080-0.140 (0.108), recall@10 0.081-0.105 (0.091).
  double min_at1;
  double min_at10;
};

// Adds the same `count` vectors from `next` under ids first, first + 1, ...
// to both indexes.
void AddToBoth(PlaceIndex& a, PlaceIndex& b, uint64_t first, size_t count,
               const std::function<Vector(std::mt19937&)>& next,
               std::mt19937& rng) {
  std::vector<uint64_t> ids;
  std::vector<Vector> vectors;
  for (uint64_t id = first; id < first + count; ++id) {
    ids.push_back(id);
    vectors.push_back(next(rng));
  }
  ASSERT_TRUE(a.Add(ids, vectors).ok());
  ASSERT_TRUE(b.Add(ids, vectors).ok());
}

TEST(FlannIndexTest, RecallAgainstExactIndexOn256dUnitVectors) {
  constexpr size_t kDimension = 256;
  constexpr size_t kStored = 5000;  // the default static memory's capacity
  constexpr size_t kQueries = 300;
  std::mt19937 blob_rng(17);
  const BlobSource blobs(kDimension, 50, 0.6f, blob_rng);
  const std::vector<RecallCase> cases = {
      {"50 blobs", [&](std::mt19937& rng) { return blobs.Next(rng); }, 0.80,
       0.82},
      // Isotropic 256-d data: the worst case for kd-trees.
      {"uniform on the sphere",
       [](std::mt19937& rng) { return RandomUnit(kDimension, rng); }, 0.04,
       0.06},
  };
  for (const RecallCase& c : cases) {
    SCOPED_TRACE(c.data);
    std::mt19937 rng(23);
    std::unique_ptr<PlaceIndex> exact = NewExactIndex(kDimension);
    std::unique_ptr<PlaceIndex> flann = NewFlannIndex(kDimension);
    AddToBoth(*exact, *flann, 0, kStored, c.next, rng);
    if (HasFatalFailure()) return;
    std::vector<Vector> queries;
    for (size_t q = 0; q < kQueries; ++q) queries.push_back(c.next(rng));
    const Recall recall = MeasureRecall(*flann, *exact, queries);
    std::cout << "[ measured ] FLANN default options (trees 4, checks 128), "
              << kStored << " x " << kDimension << "-d, " << c.data
              << ": recall@1 " << recall.at1 << ", recall@10 " << recall.at10
              << "\n";
    EXPECT_GE(recall.at1, c.min_at1);
    EXPECT_GE(recall.at10, c.min_at10);
  }
}

// Codes with a low intrinsic dimension, as learned place descriptors have:
// a 16-d gaussian latent through a fixed random 256 x 16 map, plus a little
// isotropic noise, normalised.
class LowRankSource {
 public:
  LowRankSource(size_t dimension, size_t latent, std::mt19937& rng)
      : latent_(latent) {
    for (size_t i = 0; i < dimension; ++i) {
      map_.push_back(RandomGaussian(latent, rng, 1.0f));
    }
  }
  Vector Next(std::mt19937& rng) const {
    const Vector z = RandomGaussian(latent_, rng, 1.0f);
    const Vector noise = RandomGaussian(map_.size(), rng, 0.05f);
    Vector v(map_.size());
    for (size_t i = 0; i < map_.size(); ++i) {
      float dot = 0;
      for (size_t j = 0; j < latent_; ++j) dot += map_[i][j] * z[j];
      v[i] = dot + noise[i];
    }
    return Normalized(std::move(v));
  }

 private:
  size_t latent_;
  std::vector<Vector> map_;
};

// HNSW at the paper's memory size after forgetting-like churn (a fifth
// removed, as many added into the freed nodes): recall@10 >= 0.95 on
// low-rank codes; on uniform 256-d data (no structure: the worst case for
// every graph or tree) it is lower, and the floor records what it is.
TEST(HnswIndexTest, RecallAgainstExactIndexAfterChurn) {
  constexpr size_t kDimension = 256;
  constexpr size_t kStored = 5000;
  std::mt19937 source_rng(31);
  const LowRankSource low_rank(kDimension, 16, source_rng);
  const std::vector<RecallCase> cases = {
      {"low-rank (16-d latent)",
       [&](std::mt19937& rng) { return low_rank.Next(rng); }, 0.9, 0.95},
      {"uniform on the sphere",
       [](std::mt19937& rng) { return RandomUnit(kDimension, rng); }, 0.7, 0.7},
  };
  // One batch of 5,000 and one of 1,000 (200 refills): with two insert
  // threads (the default) the batches are linked concurrently, with one in
  // order; the recall bounds are the same.
  for (const RecallCase& c : cases) {
    for (size_t threads : {1, 2}) {
      SCOPED_TRACE(absl::StrCat(c.data, ", insert_threads ", threads));
      std::mt19937 rng(29);
      std::unique_ptr<PlaceIndex> exact = NewExactIndex(kDimension);
      HnswIndexOptions options;
      options.insert_threads = threads;
      std::unique_ptr<PlaceIndex> hnsw = NewHnswIndex(kDimension, options);
      AddToBoth(*exact, *hnsw, 0, kStored, c.next, rng);
      if (HasFatalFailure()) return;
      std::vector<uint64_t> removed(kStored / 5);
      for (uint64_t id = 0; id < removed.size(); ++id) removed[id] = id;
      ASSERT_TRUE(exact->Remove(removed).ok());
      ASSERT_TRUE(hnsw->Remove(removed).ok());
      AddToBoth(*exact, *hnsw, kStored, kStored / 5, c.next, rng);
      if (HasFatalFailure()) return;
      EXPECT_EQ(hnsw->size(), kStored);
      std::vector<Vector> queries;
      for (size_t q = 0; q < 200; ++q) queries.push_back(c.next(rng));
      const Recall recall = MeasureRecall(*hnsw, *exact, queries);
      std::cout << "[ measured ] HNSW default options, insert_threads "
                << threads << ", " << kStored << " x " << kDimension << "-d, "
                << c.data << ", after 20 % churn: recall@1 " << recall.at1
                << ", recall@10 " << recall.at10 << "\n";
      EXPECT_GE(recall.at1, c.min_at1);
      EXPECT_GE(recall.at10, c.min_at10);
    }
  }
}

// ---------------------------------------------------------------------------
// The tiered index's growing segment and background indexer.

Dataset LowRankDataset(uint64_t first, size_t count,
                       const LowRankSource& source, std::mt19937& rng) {
  Dataset data;
  for (uint64_t id = first; id < first + count; ++id) {
    data.ids.push_back(id);
    data.vectors.push_back(source.Next(rng));
  }
  return data;
}

// Adds `count` low-rank vectors, in batches of `step`, to both indexes;
// after each batch its newest vector finds itself in `tiered`, whichever
// part holds it.
void AddBatchesToBoth(PlaceIndex& tiered, PlaceIndex& exact, uint64_t count,
                      uint64_t step, const LowRankSource& source,
                      std::mt19937& rng) {
  for (uint64_t first = 0; first < count; first += step) {
    const Dataset batch = LowRankDataset(first, step, source, rng);
    ASSERT_TRUE(tiered.Add(batch.ids, batch.vectors).ok());
    ASSERT_TRUE(exact.Add(batch.ids, batch.vectors).ok());
    EXPECT_EQ(tiered.size(), first + step);
    EXPECT_THAT(Ids(SearchOk(tiered, batch.vectors.back(), 1)),
                ElementsAre(batch.ids.back()));
  }
}

// recall@10 of `tiered` against `exact` on 100 new codes of `source` (left
// in *queries if given).
double RecallAt10(const PlaceIndex& tiered, const PlaceIndex& exact,
                  const LowRankSource& source, std::mt19937& rng,
                  std::vector<Vector>* queries = nullptr) {
  std::vector<Vector> mine;
  std::vector<Vector>& used = queries != nullptr ? *queries : mine;
  for (size_t q = 0; q < 100; ++q) used.push_back(source.Next(rng));
  return MeasureRecall(tiered, exact, used).at10;
}

// Every vector is searchable as soon as Add returns (from the growing
// segment), and once the background thread has drained the segment the
// graph answers as the exact index does (recall@10 on low-rank codes).
TEST(TieredIndexTest, AddedVectorsAreFoundAtOnceAndDrainIntoTheGraph) {
  constexpr size_t kDimension = 64;
  std::mt19937 rng(41);
  const LowRankSource source(kDimension, 8, rng);
  TieredIndexOptions options;
  options.hnsw_from = 500;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  std::unique_ptr<PlaceIndex> exact = NewExactIndex(kDimension);
  EXPECT_EQ(tiered->unindexed(), 0u);
  AddBatchesToBoth(*tiered, *exact, 3000, 100, source, rng);
  EXPECT_EQ(WaitForIndexing(*tiered), 0u);
  EXPECT_EQ(tiered->unindexed(), 0u);
  EXPECT_EQ(tiered->size(), 3000u);
  std::vector<Vector> queries;
  EXPECT_GE(RecallAt10(*tiered, *exact, source, rng, &queries), 0.95);
  // Below half the threshold the graph is dropped: exact answers again.
  std::vector<uint64_t> removed;
  for (uint64_t id = 0; id < 2800; ++id) removed.push_back(id);
  ASSERT_TRUE(tiered->Remove(removed).ok());
  ASSERT_TRUE(exact->Remove(removed).ok());
  EXPECT_EQ(tiered->size(), 200u);
  EXPECT_EQ(tiered->unindexed(), 0u);
  for (const Vector& query : queries) {
    EXPECT_EQ(Ids(SearchOk(*tiered, query, 10)),
              Ids(SearchOk(*exact, query, 10)));
  }
}

// A bulk load (DeferIndexing): every vector waits in the growing segment,
// found by the exact scan, with no back-pressure and nothing linked in the
// background; IndexWaiting builds the graph from all of them, which then
// answers as the exact index does.
TEST(TieredIndexTest, ADeferredGraphIsBuiltOnceByIndexWaiting) {
  constexpr size_t kDimension = 64;
  std::mt19937 rng(43);
  const LowRankSource source(kDimension, 8, rng);
  TieredIndexOptions options;
  options.hnsw_from = 500;
  options.max_unindexed = 100;  // would hold Add back, but for the deferral
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  std::unique_ptr<PlaceIndex> exact = NewExactIndex(kDimension);
  tiered->DeferIndexing(absl::InfiniteFuture());
  AddBatchesToBoth(*tiered, *exact, 3000, 250, source, rng);
  absl::SleepFor(absl::Milliseconds(50));  // a background step, if any
  EXPECT_EQ(tiered->unindexed(), 3000u);
  EXPECT_EQ(WaitForIndexing(*tiered), 3000u);  // nothing to wait for
  ASSERT_TRUE(tiered->IndexWaiting().ok());
  EXPECT_EQ(tiered->unindexed(), 0u);
  EXPECT_EQ(tiered->size(), 3000u);
  EXPECT_GE(RecallAt10(*tiered, *exact, source, rng), 0.95);
  // Without a deferral the background thread links new vectors again.
  const Dataset more = LowRankDataset(3000, 1000, source, rng);
  ASSERT_TRUE(tiered->Add(more.ids, more.vectors).ok());
  EXPECT_EQ(WaitForIndexing(*tiered), 0u);
}

// SearchParams::codes: the tiered index returns each neighbour's code as
// given (CopyCode), whichever tier holds it, in the search's turn of its
// lock.
TEST(TieredIndexTest, SearchReturnsTheCodesOfItsNeighbours) {
  constexpr size_t kDimension = 32;
  std::mt19937 rng(43);
  const LowRankSource source(kDimension, 8, rng);
  TieredIndexOptions options;
  options.hnsw_from = 200;
  options.max_unindexed = 100;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  const Dataset data = LowRankDataset(0, 1000, source, rng);
  ASSERT_TRUE(tiered->AddNormalized(data.ids, Views(data.vectors)).ok());
  for (size_t q = 0; q < 20; ++q) {
    std::vector<std::vector<float>> codes;
    SearchParams params;
    params.k = 5;
    params.unit_query = true;
    params.codes = &codes;
    absl::StatusOr<std::vector<Neighbor>> found =
        tiered->Search(data.vectors[q * 50], params);
    ASSERT_TRUE(found.ok()) << found.status();
    ASSERT_EQ(found->size(), 5u);
    ASSERT_EQ(codes.size(), 5u);
    for (size_t i = 0; i < found->size(); ++i) {
      EXPECT_EQ(codes[i], data.vectors[(*found)[i].id]);
    }
  }
}

// Back-pressure: however slow the background thread is, an Add that finds
// more than max_unindexed vectors waiting moves as many into the graph as it
// adds, so the growing segment never exceeds the switch size or the bound
// by more than one batch.
TEST(TieredIndexTest, GrowingSegmentStaysBounded) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(43);
  TieredIndexOptions options;
  options.hnsw_from = 50;
  options.max_unindexed = 20;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  for (uint64_t first = 0; first < 2000; first += 10) {
    const Dataset batch = GaussianDataset(10, kDimension, rng, first);
    ASSERT_TRUE(tiered->Add(batch.ids, batch.vectors).ok());
    EXPECT_LE(tiered->unindexed(), 50u + 10u);
  }
  EXPECT_EQ(tiered->size(), 2000u);
}

// The engine's way: an unthrottled add under its own lock, then CatchUp
// outside it does the same back-pressure.
TEST(TieredIndexTest, CatchUpAfterAnUnthrottledAddKeepsTheSegmentBounded) {
  constexpr size_t kDimension = 16;
  std::mt19937 rng(43);
  TieredIndexOptions options;
  options.hnsw_from = 50;
  options.max_unindexed = 20;
  options.indexer_batch = 1;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  size_t most = 0;
  for (uint64_t first = 0; first < 2000; first += 10) {
    const Dataset batch = GaussianDataset(10, kDimension, rng, first);
    const std::vector<std::span<const float>> codes(batch.vectors.begin(),
                                                    batch.vectors.end());
    ASSERT_TRUE(tiered->AddNormalizedUnthrottled(batch.ids, codes).ok());
    most = std::max(most, tiered->unindexed());
    ASSERT_TRUE(tiered->CatchUp(batch.ids.size()).ok());
    EXPECT_LE(tiered->unindexed(), 50u + 10u);
  }
  EXPECT_GT(most, options.max_unindexed);  // the add itself was not held up
  EXPECT_EQ(tiered->size(), 2000u);
}

// A bulk load (a restart) goes into the growing segment in one call without
// waiting for the graph; a used id is refused whichever part holds it.
TEST(TieredIndexTest, BulkAddReturnsBeforeTheGraphIsBuilt) {
  constexpr size_t kDimension = 32;
  std::mt19937 rng(47);
  TieredIndexOptions options;
  options.hnsw_from = 100;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  const Dataset data = GaussianDataset(5000, kDimension, rng);
  ASSERT_TRUE(tiered->Add(data.ids, data.vectors).ok());
  EXPECT_EQ(tiered->size(), 5000u);
  WaitForIndexing(*tiered);
  EXPECT_EQ(tiered->unindexed(), 0u);
  absl::Status used = tiered->Add(std::vector<uint64_t>{17},
                                  std::vector<Vector>{data.vectors[0]});
  EXPECT_EQ(used.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(used.message(), HasSubstr("id 17"));
  EXPECT_EQ(tiered->size(), 5000u);
}

// A load's add (what a restart puts back beside its index snapshot) is not
// held up by back-pressure, however large the backlog: the background
// thread catches up. An upload's add with the same backlog would move as
// many vectors into the graph as it adds before returning.
TEST(TieredIndexTest, LoadAddIsNotThrottledByTheBacklog) {
  constexpr size_t kDimension = 256;
  std::mt19937 rng(59);
  TieredIndexOptions options;
  options.hnsw_from = 100;
  options.max_unindexed = 100;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  const Dataset first = GaussianDataset(3000, kDimension, rng);
  ASSERT_TRUE(tiered->Add(first.ids, first.vectors).ok());
  const Dataset second = GaussianDataset(3000, kDimension, rng, 3000);
  std::vector<std::span<const float>> codes(second.vectors.begin(),
                                            second.vectors.end());
  ASSERT_TRUE(tiered->AddNormalizedUnthrottled(second.ids, codes).ok());
  // Throttled, at most 3000 could still wait; the graph inserts a few
  // thousand 256-d vectors per second here.
  EXPECT_GT(tiered->unindexed(), 4500u);
  EXPECT_EQ(tiered->size(), 6000u);
  EXPECT_EQ(WaitForIndexing(*tiered), 0u);
  EXPECT_TRUE(tiered->HoldsCode(5999));
}

// Searches from several threads while the engine's single writer adds and
// removes and the background thread moves vectors: every answer is sorted,
// holds no id twice and no id removed before the search began.
TEST(TieredIndexTest, SearchesDuringBackgroundIndexingSeeEachVectorOnce) {
  constexpr size_t kDimension = 48;
  std::mt19937 rng(53);
  TieredIndexOptions options;
  options.hnsw_from = 200;
  options.indexer_batch = 4;
  std::unique_ptr<PlaceIndex> tiered = NewTieredIndex(kDimension, options);
  std::atomic<uint64_t> removed_below{0};
  std::atomic<bool> done{false};
  std::vector<std::thread> readers;
  std::atomic<int> bad{0};
  for (int t = 0; t < 2; ++t) {
    readers.emplace_back([&, t] {
      std::mt19937 local(100 + t);
      while (!done.load()) {
        const uint64_t floor = removed_below.load();
        absl::StatusOr<std::vector<Neighbor>> found =
            tiered->Search(RandomGaussian(kDimension, local), {20, {}});
        if (!found.ok()) {
          ++bad;
          continue;
        }
        std::set<uint64_t> seen;
        for (size_t i = 0; i < found->size(); ++i) {
          const Neighbor& n = (*found)[i];
          if (!seen.insert(n.id).second || n.id < floor ||
              (i > 0 && n.distance < (*found)[i - 1].distance)) {
            ++bad;
          }
        }
      }
    });
  }
  for (uint64_t first = 0; first < 6000; first += 50) {
    const Dataset batch = GaussianDataset(50, kDimension, rng, first);
    ASSERT_TRUE(tiered->Add(batch.ids, batch.vectors).ok());
    if (first >= 1000) {
      // Removes the oldest 25 before the floor moves past them.
      std::vector<uint64_t> old;
      const uint64_t from = removed_below.load();
      for (uint64_t id = from; id < from + 25; ++id) old.push_back(id);
      ASSERT_TRUE(tiered->Remove(old).ok());
      removed_below.store(from + 25);
    }
  }
  done.store(true);
  for (std::thread& reader : readers) reader.join();
  EXPECT_EQ(bad.load(), 0);
  EXPECT_EQ(tiered->size(), 6000u - removed_below.load());
}

// Whatever byte of a graph snapshot is damaged, Load refuses it or the
// loaded graph is safe to search (ASan runs this): links, levels, slots and
// counts are all checked. (On disk a checksum refuses damage first.)
TEST(HnswIndexTest, DamagedSnapshotIsRefusedOrSafeToSearch) {
  constexpr size_t kDimension = 4;
  std::mt19937 rng(19);
  std::unique_ptr<PlaceIndex> index = NewHnswIndex(kDimension);
  Dataset data = GaussianDataset(300, kDimension, rng);
  ASSERT_TRUE(index->Add(data.ids, data.vectors).ok());
  ASSERT_TRUE(index->Remove(std::vector<uint64_t>{5, 6, 7}).ok());
  absl::StatusOr<std::string> bytes = Saved(*index);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  std::uniform_int_distribution<size_t> position(0, bytes->size() - 1);
  std::uniform_int_distribution<int> value(0, 255);
  int refused = 0;
  for (int trial = 0; trial < 300; ++trial) {
    std::string damaged = *bytes;
    damaged[position(rng)] = static_cast<char>(value(rng));
    std::unique_ptr<PlaceIndex> loaded = NewHnswIndex(kDimension);
    if (!LoadFrom(*loaded, damaged).ok()) {
      ++refused;
      continue;
    }
    for (int q = 0; q < 5; ++q) {
      EXPECT_LE(SearchOk(*loaded, RandomGaussian(kDimension, rng), 5).size(),
                5u);
    }
  }
  std::cout << "[ measured ] damaged HNSW snapshots refused: " << refused
            << " / 300\n";
  EXPECT_GT(refused, 0);
}

// A graph node holds its code as given with its scale and the scaled
// squared norm the walk uses; a snapshot whose scale or norm is not a
// finite, non-negative number is refused rather than searched with
// distances that mean nothing.
HnswIndexOptions FloatCodes() {
  HnswIndexOptions options;
  options.codes = HnswIndexOptions::Codes::kFloat;
  return options;
}

// The snapshot of an HNSW index of 4-d vectors made with `options`: 50
// gaussian ones and, as id 1000, one whose bytes are easy to find: (2, 0,
// 0, 0), scale 1 (Add takes vectors as they are).
absl::StatusOr<std::string> SavedWithAMarkedNode(HnswIndexOptions options) {
  std::mt19937 rng(29);
  std::unique_ptr<PlaceIndex> index = NewHnswIndex(4, options);
  Dataset data = GaussianDataset(50, 4, rng);
  data.ids.push_back(1000);
  data.vectors.push_back({2.0f, 0.0f, 0.0f, 0.0f});
  if (absl::Status added = index->Add(data.ids, data.vectors); !added.ok()) {
    return added;
  }
  return Saved(*index);
}

TEST(HnswIndexTest, SnapshotWithABadScaleOrNormIsRefused) {
  constexpr size_t kDimension = 4;
  absl::StatusOr<std::string> bytes = SavedWithAMarkedNode(FloatCodes());
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  // The marked node's squared norm is 4.
  const float node[] = {2.0f, 0.0f, 0.0f, 0.0f, 1.0f, 4.0f};
  const size_t at = bytes->find(
      std::string(reinterpret_cast<const char*>(node), sizeof node));
  ASSERT_NE(at, std::string::npos);
  ASSERT_TRUE(LoadFrom(*NewHnswIndex(kDimension, FloatCodes()), *bytes).ok());
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  for (const auto& [field, value] : std::vector<std::pair<int, float>>{
           {4, nan}, {4, inf}, {4, -0.5f}, {5, nan}, {5, -1.0f}, {5, inf}}) {
    std::string damaged = *bytes;
    std::memcpy(damaged.data() + at + field * sizeof(float), &value,
                sizeof value);
    EXPECT_EQ(LoadFrom(*NewHnswIndex(kDimension, FloatCodes()), damaged).code(),
              absl::StatusCode::kDataLoss)
        << (field == 4 ? "scale " : "norm ") << value;
  }
}

// The same for an int8 graph: its node's step and squared norm, and the
// scale kept with its floats; a float graph's snapshot does not load as an
// int8 one (a server whose hnsw.codes changed rebuilds).
TEST(HnswIndexTest, Int8SnapshotWithABadStepNormOrScaleIsRefused) {
  constexpr size_t kDimension = 4;
  absl::StatusOr<std::string> bytes = SavedWithAMarkedNode({});
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  // The node: step 2/127, squared norm step² 127², then 127 and zeros.
  const float step = 2.0f / 127.0f;
  const float header[] = {step, step * step * static_cast<float>(127 * 127)};
  std::string node(reinterpret_cast<const char*>(header), sizeof header);
  node += std::string(1, static_cast<char>(127)) + std::string(15, '\0');
  const size_t at_node = bytes->find(node);
  ASSERT_NE(at_node, std::string::npos);
  const float floats[] = {2.0f, 0.0f, 0.0f, 0.0f, 1.0f};  // and its scale
  const size_t at_floats = bytes->find(
      std::string(reinterpret_cast<const char*>(floats), sizeof floats));
  ASSERT_NE(at_floats, std::string::npos);
  ASSERT_TRUE(LoadFrom(*NewHnswIndex(kDimension), *bytes).ok());
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();
  for (size_t offset :
       {at_node, at_node + sizeof(float), at_floats + 4 * sizeof(float)}) {
    for (float value : {nan, inf, -0.5f}) {
      std::string damaged = *bytes;
      std::memcpy(damaged.data() + offset, &value, sizeof value);
      EXPECT_EQ(LoadFrom(*NewHnswIndex(kDimension), damaged).code(),
                absl::StatusCode::kDataLoss)
          << "at " << offset << ": " << value;
    }
  }
  absl::StatusOr<std::string> float_bytes = SavedWithAMarkedNode(FloatCodes());
  ASSERT_TRUE(float_bytes.ok());
  EXPECT_EQ(LoadFrom(*NewHnswIndex(kDimension), *float_bytes).code(),
            absl::StatusCode::kDataLoss);
}

// Each kind of index refuses another kind's bytes (a server restarted with
// another `index` setting rebuilds).
TEST(IndexSnapshotTest, AnotherKindsBytesAreDataLoss) {
  std::mt19937 rng(23);
  Dataset data = GaussianDataset(40, 8, rng);
  std::unique_ptr<PlaceIndex> exact = NewExactIndex(8);
  ASSERT_TRUE(exact->Add(data.ids, data.vectors).ok());
  absl::StatusOr<std::string> bytes = Saved(*exact);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  EXPECT_EQ(LoadFrom(*NewHnswIndex(8), *bytes).code(),
            absl::StatusCode::kDataLoss);
  EXPECT_EQ(LoadFrom(*NewTieredIndex(8), *bytes).code(),
            absl::StatusCode::kDataLoss);
  EXPECT_EQ(LoadFrom(*NewFlannIndex(8), *bytes).code(),
            absl::StatusCode::kUnimplemented);
}

// A fresh directory of its own under the test's temporary directory.
std::string FreshDirectory() {
  std::string path = ::testing::TempDir() + "/floats-XXXXXX";
  EXPECT_NE(::mkdtemp(path.data()), nullptr);
  return path;
}

// Rows written are read back bit for bit; the file is unlinked as it is
// made (the directory stays empty: nothing is left after the process), and
// the process's own memory holds none of them.
TEST(FileFloatRowsTest, RowsComeBackAndTheFileIsNowhereToBeSeen) {
  const std::string directory = FreshDirectory();
  FileFloatRows rows(directory, 5);
  rows.Reserve(3);
  EXPECT_GE(rows.reserved(), 3u);
  EXPECT_TRUE(std::filesystem::is_empty(directory));
  const std::vector<float> values = {1,  2,  3,    4,    5,    -1,   -2,  -3,
                                     -4, -5, 0.1f, 0.2f, 0.3f, 0.4f, 0.5f};
  rows.Write(0, 3, values.data());
  rows.Reserve(5000);  // grows; what was written stays
  const std::vector<float> last = {9, 8, 7, 6, 5};
  rows.Write(4999, 1, last.data());
  std::vector<float> read(15);
  rows.Read(0, 3, read.data());
  EXPECT_EQ(read, values);
  read.resize(5);
  rows.Read(4999, 1, read.data());
  EXPECT_EQ(read, last);
  EXPECT_EQ(rows.Find(0), nullptr);
  EXPECT_EQ(rows.MemoryBytes(), 0u);
  std::filesystem::remove(directory);
}

// This process's descriptors of the floats' files made in `directory`
// (unlinked: found through /proc/self/fd).
std::vector<int> FloatFileDescriptors(const std::string& directory) {
  const std::string made =
      std::filesystem::canonical(directory).string() + "/graph-floats-";
  std::vector<int> descriptors;
  for (const auto& entry :
       std::filesystem::directory_iterator("/proc/self/fd")) {
    std::error_code error;
    const std::string target =
        std::filesystem::read_symlink(entry.path(), error).string();
    if (error || target.rfind(made, 0) != 0) continue;
    descriptors.push_back(std::stoi(entry.path().filename().string()));
  }
  return descriptors;
}

// Writes the file of each FileFloatRows made in `directory` back and drops
// its pages from the page cache, so that the next reads go to the disk.
void DropFloatsFromPageCache(const std::string& directory) {
  int dropped = 0;
  for (const int fd : FloatFileDescriptors(directory)) {
    ASSERT_EQ(::fdatasync(fd), 0);
    ASSERT_EQ(::posix_fadvise(fd, 0, 0, POSIX_FADV_DONTNEED), 0);
    ++dropped;
  }
  ASSERT_GT(dropped, 0) << "no floats' file made in " << directory
                        << " is open";
}

// Gather hands back the rows asked, in the order asked and repeated where
// asked, bit for bit, whether the page cache holds them (read without
// waiting) or not (their reads started together, then waited for); a row
// past the file's end is an I/O error the caller sees.
TEST(FileFloatRowsTest, GatherReadsRowsInTheCacheAndOffIt) {
  constexpr size_t kWidth = 257;  // rows across page boundaries
  constexpr size_t kRows = 3000;
  const std::string directory = FreshDirectory();
  FileFloatRows rows(directory, kWidth);
  rows.Reserve(kRows);
  std::mt19937 rng(61);
  std::normal_distribution<float> normal;
  std::vector<float> values(kRows * kWidth);
  for (float& value : values) value = normal(rng);
  rows.Write(0, kRows, values.data());
  const std::vector<uint32_t> asked = {2999, 0, 1500, 1500, 16, 17, 4, 2999};
  for (const bool cold : {true, false}) {
    if (cold) DropFloatsFromPageCache(directory);
    std::vector<float> gathered(asked.size() * kWidth, -1.0f);
    rows.Gather(asked, gathered.data());
    for (size_t i = 0; i < asked.size(); ++i) {
      EXPECT_TRUE(std::equal(gathered.begin() + i * kWidth,
                             gathered.begin() + (i + 1) * kWidth,
                             values.begin() + asked[i] * kWidth))
          << "row " << asked[i] << (cold ? " off the page cache" : "");
    }
  }
  const std::vector<uint32_t> past_end = {
      1, static_cast<uint32_t>(rows.reserved() + 10)};
  std::vector<float> gathered(past_end.size() * kWidth);
  EXPECT_THROW(rows.Gather(past_end, gathered.data()), std::system_error);
  std::filesystem::remove(directory);
}

// A directory that cannot hold the file is an error the caller sees
// (std::system_error naming it), not a crash; an index given such a
// directory adds nothing and says why, and its searches go on.
TEST(FileFloatRowsTest, ADirectoryThatCannotHoldTheFloatsAddsNothing) {
  const std::string missing = ::testing::TempDir() + "/no-such-directory";
  FileFloatRows rows(missing, 4);
  try {
    rows.Reserve(1);
    ADD_FAILURE() << "Reserve in a missing directory succeeded";
  } catch (const std::system_error& e) {
    EXPECT_THAT(e.what(), HasSubstr("no-such-directory"));
  }
  HnswIndexOptions options;
  options.floats_dir = missing;
  std::unique_ptr<PlaceIndex> index = NewHnswIndex(4, options);
  const absl::Status added =
      index->Add(std::vector<uint64_t>{1, 2},
                 std::vector<Vector>{{1, 0, 0, 0}, {0, 1, 0, 0}});
  EXPECT_EQ(added.code(), absl::StatusCode::kResourceExhausted) << added;
  EXPECT_THAT(added.message(), HasSubstr("nothing added"));
  EXPECT_EQ(index->size(), 0u);
  EXPECT_THAT(SearchOk(*index, {1, 0, 0, 0}, 3), IsEmpty());
}

// An int8 index whose floats are in a file answers as one whose floats are
// on the heap: the same neighbours at the same distances, the same codes
// bit for bit, the same snapshot bytes; a snapshot loads into either.
TEST(HnswIndexTest, FloatsInAFileAnswerAsFloatsOnTheHeap) {
  constexpr size_t kDimension = 24;
  std::mt19937 rng(41);
  const Dataset data = GaussianDataset(2000, kDimension, rng);
  HnswIndexOptions heap_options;
  heap_options.insert_threads = 1;  // the same graph from the same adds
  HnswIndexOptions file_options = heap_options;
  const std::string directory = FreshDirectory();
  file_options.floats_dir = directory;
  std::unique_ptr<PlaceIndex> heap = NewHnswIndex(kDimension, heap_options);
  std::unique_ptr<PlaceIndex> file = NewHnswIndex(kDimension, file_options);
  std::vector<std::span<const float>> codes(data.vectors.begin(),
                                            data.vectors.end());
  ASSERT_TRUE(heap->AddNormalized(data.ids, codes).ok());
  ASSERT_TRUE(file->AddNormalized(data.ids, codes).ok());
  ASSERT_TRUE(heap->Remove(std::vector<uint64_t>{3, 5, 7}).ok());
  ASSERT_TRUE(file->Remove(std::vector<uint64_t>{3, 5, 7}).ok());
  const Dataset queries = GaussianDataset(30, kDimension, rng);
  ExpectSameAnswers(*heap, *file, queries.vectors);
  std::vector<float> from_heap, from_file;
  for (uint64_t id : {0, 11, 999, 1999}) {
    ASSERT_TRUE(heap->CopyCode(data.ids[id], &from_heap));
    ASSERT_TRUE(file->CopyCode(data.ids[id], &from_file));
    EXPECT_EQ(from_file, from_heap);
    EXPECT_EQ(from_file, data.vectors[id]);
  }
  // CopyCodes: the held ids' codes in one batch off the page cache, an id
  // not held left as it was and said so.
  DropFloatsFromPageCache(directory);
  const std::vector<uint64_t> batch = {data.ids[1999], 3, data.ids[0],
                                       data.ids[500]};
  std::vector<std::vector<float>> copies(batch.size(), {-7.0f});
  std::vector<std::vector<float>*> targets;
  for (auto& copy : copies) targets.push_back(&copy);
  EXPECT_FALSE(file->CopyCodes(batch, targets));  // 3 was removed
  EXPECT_EQ(copies[0], data.vectors[1999]);
  EXPECT_EQ(copies[1], std::vector<float>{-7.0f});
  EXPECT_EQ(copies[2], data.vectors[0]);
  EXPECT_EQ(copies[3], data.vectors[500]);
  ExpectSameAnswers(*heap, *file, queries.vectors);
  absl::StatusOr<std::string> heap_bytes = Saved(*heap);
  absl::StatusOr<std::string> file_bytes = Saved(*file);
  ASSERT_TRUE(heap_bytes.ok() && file_bytes.ok());
  EXPECT_TRUE(*heap_bytes == *file_bytes);
  std::unique_ptr<PlaceIndex> loaded = NewHnswIndex(kDimension, file_options);
  ASSERT_TRUE(LoadFrom(*loaded, *heap_bytes).ok());
  ExpectSameAnswers(*heap, *loaded, queries.vectors);
  ASSERT_TRUE(loaded->CopyCode(data.ids[42], &from_file));
  EXPECT_EQ(from_file, data.vectors[42]);
  EXPECT_TRUE(std::filesystem::is_empty(directory));
  std::filesystem::remove(directory);
}

// A file holding `bytes` after `prefix` bytes of zeros, open for reading,
// as the store hands a snapshot's payload to a reader (the descriptor
// closed with its last holder; the file itself is unlinked at once).
core::FileBytes FileHolding(const std::string& directory,
                            std::string_view bytes, size_t prefix) {
  std::string path = directory + "/held-XXXXXX";
  const int fd = ::mkostemp(path.data(), O_CLOEXEC);
  EXPECT_GE(fd, 0);
  ::unlink(path.c_str());
  const std::string zeros(prefix, '\0');
  EXPECT_EQ(::pwrite(fd, zeros.data(), zeros.size(), 0),
            static_cast<ssize_t>(prefix));
  EXPECT_EQ(::pwrite(fd, bytes.data(), bytes.size(), prefix),
            static_cast<ssize_t>(bytes.size()));
  return {.descriptor = std::shared_ptr<const int>(new int(fd),
                                                   [](const int* held) {
                                                     ::close(*held);
                                                     delete held;
                                                   }),
          .offset = prefix};
}

// The disk blocks (st_blocks) of the floats' files made in `directory`
// that this process holds open, and how many there are.
std::pair<size_t, int> FloatFilesInUse(const std::string& directory) {
  size_t bytes = 0;
  int files = 0;
  for (const int fd : FloatFileDescriptors(directory)) {
    struct stat info;
    if (::fstat(fd, &info) != 0) continue;
    bytes += static_cast<size_t>(info.st_blocks) * 512;
    ++files;
  }
  return {bytes, files};
}

// Adopted rows are read from the file they lie in (no copy: a change to
// that file, which a store never makes, shows through) until a row is
// written again; the rows' own file takes no block for them.
TEST(FileFloatRowsTest, AdoptedRowsAreReadFromTheirFileUntilWrittenAgain) {
  constexpr size_t kWidth = 257;
  constexpr size_t kRows = 2000;
  const size_t row_bytes = kWidth * sizeof(float);
  const std::string directory = FreshDirectory();
  std::mt19937 rng(67);
  std::normal_distribution<float> normal;
  std::vector<float> values(kRows * kWidth);
  for (float& value : values) value = normal(rng);
  const core::FileBytes file =
      FileHolding(directory,
                  std::string_view(reinterpret_cast<const char*>(values.data()),
                                   values.size() * sizeof(float)),
                  /*prefix=*/100);
  FileFloatRows rows(directory, kWidth);
  ASSERT_TRUE(rows.Adopt(file, 100, kRows, {}, {}));
  EXPECT_EQ(rows.adopted(), kRows);
  std::vector<float> read(kRows * kWidth);
  rows.Read(0, kRows, read.data());
  EXPECT_EQ(read, values);
  EXPECT_EQ(rows.AllocatedBytes(), 0u);  // no file of its own yet

  // A row written again is the rows' own; its neighbours are still the
  // adopted file's; rows past the adopted ones are reserved and written
  // as before.
  std::vector<float> row7(kWidth, 7.0f);
  rows.Write(7, 1, row7.data());
  rows.Reserve(kRows + 1);
  std::vector<float> past(kWidth, -3.0f);
  rows.Write(kRows, 1, past.data());
  std::vector<float> expected = values;
  std::copy(row7.begin(), row7.end(), expected.begin() + 7 * kWidth);
  expected.insert(expected.end(), past.begin(), past.end());
  read.assign((kRows + 1) * kWidth, 0.0f);
  rows.Read(0, kRows + 1, read.data());
  EXPECT_EQ(read, expected);
  const std::vector<uint32_t> asked = {kRows, 7, 6, 8, 1999, 7};
  std::vector<float> gathered(asked.size() * kWidth);
  rows.Gather(asked, gathered.data());
  for (size_t i = 0; i < asked.size(); ++i) {
    EXPECT_TRUE(std::equal(gathered.begin() + i * kWidth,
                           gathered.begin() + (i + 1) * kWidth,
                           expected.begin() + asked[i] * kWidth))
        << "row " << asked[i];
  }
  // Its own file holds row 7 and the rows reserved past the adopted ones,
  // not the adopted rows.
  EXPECT_GT(rows.AllocatedBytes(), 0u);
  EXPECT_LT(rows.AllocatedBytes(), kRows * row_bytes / 2);

  // Not a copy: the adopted file's row 6 changed shows through (row 7,
  // written since, does not).
  std::vector<float> changed(2 * kWidth, 42.0f);
  ASSERT_EQ(::pwrite(*file.descriptor, changed.data(), 2 * row_bytes,
                     100 + 6 * row_bytes),
            static_cast<ssize_t>(2 * row_bytes));
  read.assign(2 * kWidth, 0.0f);
  rows.Read(6, 2, read.data());
  EXPECT_TRUE(std::all_of(read.begin(), read.begin() + kWidth,
                          [](float v) { return v == 42.0f; }));
  EXPECT_TRUE(std::equal(read.begin() + kWidth, read.end(), row7.begin()));
  std::filesystem::remove_all(directory);
}

// Rows adopted with their checks (a snapshot whose checksum leaves them
// out) are checked as they are read: a damaged row is a std::system_error
// of std::errc::bad_message from Read and from Gather, its neighbours read
// as they were, and a row written again since is the rows' own (unchecked).
TEST(FileFloatRowsTest, AdoptedRowsWithChecksAreCheckedWhenRead) {
  constexpr size_t kWidth = 257;
  constexpr size_t kRows = 300;
  const size_t row_bytes = kWidth * sizeof(float);
  const std::string directory = FreshDirectory();
  std::vector<float> values(kRows * kWidth);
  for (size_t i = 0; i < values.size(); ++i) values[i] = 0.5f * i;
  std::vector<uint32_t> checks(kRows);
  for (size_t row = 0; row < kRows; ++row) {
    checks[row] = core::RowCheck({values.data() + row * kWidth, kWidth});
  }
  std::string bytes(reinterpret_cast<const char*>(values.data()),
                    values.size() * sizeof(float));
  bytes[40 * row_bytes + 17] ^= 0x04;  // row 40
  bytes[41 * row_bytes + 3] ^= 0x04;   // row 41, written again below
  const core::FileBytes file = FileHolding(directory, bytes, /*prefix=*/8);
  FileFloatRows rows(directory, kWidth);
  ASSERT_TRUE(rows.Adopt(file, 8, kRows, {}, checks));
  rows.Write(41, 1, values.data() + 41 * kWidth);
  std::vector<float> read(kWidth);
  auto fails_its_check = [](const std::function<void()>& call) {
    try {
      call();
    } catch (const std::system_error& e) {
      return e.code() == std::errc::bad_message &&
             std::string(e.what()).find("row 40 ") != std::string::npos;
    }
    return false;
  };
  EXPECT_TRUE(fails_its_check([&] { rows.Read(40, 1, read.data()); }));
  std::vector<float> many(kRows * kWidth);
  EXPECT_TRUE(fails_its_check([&] { rows.Read(0, kRows, many.data()); }));
  const std::vector<uint32_t> asked = {39, 40, 41};
  std::vector<float> gathered(asked.size() * kWidth);
  EXPECT_TRUE(fails_its_check([&] { rows.Gather(asked, gathered.data()); }));
  for (const uint32_t row : {39u, 41u, 42u}) {
    rows.Read(row, 1, read.data());
    EXPECT_TRUE(
        std::equal(read.begin(), read.end(), values.begin() + row * kWidth))
        << row;
  }
  // Checks for fewer rows than adopted: not taken.
  FileFloatRows short_checks(directory, kWidth);
  EXPECT_FALSE(
      short_checks.Adopt(file, 8, kRows, {}, std::vector<uint32_t>(kRows - 1)));
  std::filesystem::remove_all(directory);
}

// Adopting rows a store wrote itself (a graph just saved) frees their
// blocks in its file but those of the rows written since (`keep`), which
// it goes on reading as its own.
TEST(FileFloatRowsTest, AdoptingSavedRowsKeepsTheRowsWrittenSince) {
  constexpr size_t kWidth = 257;
  constexpr size_t kRows = 2000;
  const size_t row_bytes = kWidth * sizeof(float);
  const std::string directory = FreshDirectory();
  std::vector<float> saved(kRows * kWidth);
  for (size_t i = 0; i < saved.size(); ++i) saved[i] = static_cast<float>(i);
  FileFloatRows rows(directory, kWidth);
  rows.Reserve(kRows);
  rows.Write(0, kRows, saved.data());
  const core::FileBytes file =
      FileHolding(directory,
                  std::string_view(reinterpret_cast<const char*>(saved.data()),
                                   saved.size() * sizeof(float)),
                  /*prefix=*/0);
  const size_t before = rows.AllocatedBytes();
  EXPECT_GE(before, kRows * row_bytes);
  std::vector<float> since(kWidth, -1.0f);
  rows.Write(5, 1, since.data());
  rows.Write(1500, 1, since.data());
  const std::vector<uint32_t> keep = {5, 1500};
  ASSERT_TRUE(rows.Adopt(file, 0, kRows, keep, {}));
  EXPECT_LT(rows.AllocatedBytes(), before / 4);
  std::vector<float> expected = saved;
  for (const uint32_t row : keep) {
    std::copy(since.begin(), since.end(), expected.begin() + row * kWidth);
  }
  std::vector<float> read(kRows * kWidth);
  rows.Read(0, kRows, read.data());
  EXPECT_EQ(read, expected);
  std::filesystem::remove_all(directory);
}

// An HNSW index (int8 codes, one insert thread: the same graph from the
// same adds) holding `data`'s codes as uploaded, its floats in
// `floats_dir` (on the heap when empty).
std::unique_ptr<PlaceIndex> Int8IndexHolding(const Dataset& data,
                                             size_t dimension,
                                             const std::string& floats_dir) {
  HnswIndexOptions options;
  options.insert_threads = 1;
  options.floats_dir = floats_dir;
  std::unique_ptr<PlaceIndex> index = NewHnswIndex(dimension, options);
  const std::vector<std::span<const float>> codes(data.vectors.begin(),
                                                  data.vectors.end());
  EXPECT_TRUE(index->AddNormalized(data.ids, codes).ok());
  return index;
}

// An int8 graph loaded from a snapshot that lies in a file (as the RocksDB
// store hands it over) makes no floats' file until it writes a row: its
// floats are read from the snapshot's. Answers and codes are those of the
// saved index, and stay those of a copy loaded from memory through later
// changes.
TEST(HnswIndexTest, AGraphLoadedFromAFileReadsItsFloatsThere) {
  constexpr size_t kDimension = 24;
  std::mt19937 rng(43);
  const Dataset data = GaussianDataset(2000, kDimension, rng);
  const std::string directory = FreshDirectory();
  std::unique_ptr<PlaceIndex> index =
      Int8IndexHolding(data, kDimension, directory);
  ASSERT_TRUE(index->Remove(std::vector<uint64_t>{3, 5, 7}).ok());
  HnswIndexOptions options;
  options.insert_threads = 1;
  options.floats_dir = directory;
  absl::StatusOr<std::string> bytes = Saved(*index);
  ASSERT_TRUE(bytes.ok()) << bytes.status();
  index.reset();
  ASSERT_EQ(FloatFilesInUse(directory).second, 0);

  const core::FileBytes file = FileHolding(directory, *bytes, 64);
  std::unique_ptr<PlaceIndex> from_file = NewHnswIndex(kDimension, options);
  core::ByteReader in(*bytes, &file);
  ASSERT_TRUE(from_file->Load(in).ok());
  EXPECT_EQ(FloatFilesInUse(directory).second, 0);
  std::unique_ptr<PlaceIndex> copied = NewHnswIndex(kDimension, options);
  ASSERT_TRUE(LoadFrom(*copied, *bytes).ok());
  const Dataset queries = GaussianDataset(30, kDimension, rng);
  ExpectSameAnswers(*copied, *from_file, queries.vectors);
  std::vector<float> code;
  for (uint64_t id : {0, 11, 999, 1999}) {
    ASSERT_TRUE(from_file->CopyCode(data.ids[id], &code));
    EXPECT_EQ(code, data.vectors[id]);
  }
  // Removed slots reused and new ones added: the rows written go to a file
  // of the graph's own, the rest are still read from the snapshot's.
  const Dataset more = GaussianDataset(10, kDimension, rng, 5000);
  std::vector<std::span<const float>> more_codes(more.vectors.begin(),
                                                 more.vectors.end());
  for (PlaceIndex* each : {copied.get(), from_file.get()}) {
    ASSERT_TRUE(each->AddNormalized(more.ids, more_codes).ok());
  }
  ExpectSameAnswers(*copied, *from_file, queries.vectors);
  ASSERT_TRUE(from_file->CopyCode(more.ids[0], &code));
  EXPECT_EQ(code, more.vectors[0]);
  ASSERT_TRUE(from_file->CopyCode(data.ids[1998], &code));
  EXPECT_EQ(code, data.vectors[1998]);
  absl::StatusOr<std::string> again = Saved(*from_file);
  absl::StatusOr<std::string> copied_again = Saved(*copied);
  ASSERT_TRUE(again.ok() && copied_again.ok());
  EXPECT_TRUE(*again == *copied_again);
  from_file.reset();
  copied.reset();
  std::filesystem::remove_all(directory);
}

// Once a Save to a file is in it (PlaceIndex::SavedToFile), an int8 graph
// reads its floats from there and frees its own file's blocks, but for the
// rows written after the Save read them (a removed slot reused), which it
// keeps: the same answers and codes as a twin whose floats stay on the
// heap.
TEST(HnswIndexTest, ASavedGraphReadsItsFloatsFromTheSnapshot) {
  constexpr size_t kDimension = 24;
  std::mt19937 rng(47);
  const Dataset data = GaussianDataset(3000, kDimension, rng);
  const std::string directory = FreshDirectory();
  std::unique_ptr<PlaceIndex> heap = Int8IndexHolding(data, kDimension, "");
  std::unique_ptr<PlaceIndex> file =
      Int8IndexHolding(data, kDimension, directory);
  const size_t own_before = FloatFilesInUse(directory).first;
  EXPECT_GE(own_before, 3000 * (kDimension + 1) * sizeof(float));

  // Saved to a file through a writer that says where its bytes go.
  std::string saved;
  const core::FileBytes target = FileHolding(directory, "", 0);
  {
    core::ByteWriter out(
        [&](std::span<const char> data) {
          ASSERT_EQ(::pwrite(*target.descriptor, data.data(), data.size(),
                             static_cast<off_t>(saved.size())),
                    static_cast<ssize_t>(data.size()));
          saved.append(data.data(), data.size());
        },
        &target);
    ASSERT_TRUE(file->Save(out).ok());
  }
  // Written after the Save read the floats: a removed slot reused.
  const Dataset more = GaussianDataset(1, kDimension, rng, 9000);
  std::vector<std::span<const float>> more_codes(more.vectors.begin(),
                                                 more.vectors.end());
  for (PlaceIndex* each : {heap.get(), file.get()}) {
    ASSERT_TRUE(each->Remove(std::vector<uint64_t>{data.ids[100]}).ok());
    ASSERT_TRUE(each->AddNormalized(more.ids, more_codes).ok());
  }
  file->SavedToFile();
  // What stays: the block of the row written since and the rows reserved
  // past the saved ones (a quarter more than the 3,000).
  EXPECT_LT(FloatFilesInUse(directory).first, own_before / 2);
  const Dataset queries = GaussianDataset(30, kDimension, rng);
  ExpectSameAnswers(*heap, *file, queries.vectors);
  std::vector<float> code;
  ASSERT_TRUE(file->CopyCode(more.ids[0], &code));
  EXPECT_EQ(code, more.vectors[0]);
  for (uint64_t id : {0, 99, 101, 2999}) {
    ASSERT_TRUE(file->CopyCode(data.ids[id], &code));
    EXPECT_EQ(code, data.vectors[id]);
  }
  // A second call has no Save to adopt: nothing changes.
  file->SavedToFile();
  ExpectSameAnswers(*heap, *file, queries.vectors);
  file.reset();
  std::filesystem::remove_all(directory);
}

}  // namespace
}  // namespace fleetmem::index
