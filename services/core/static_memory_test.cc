#include "services/core/static_memory.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <map>
#include <memory>
#include <random>
#include <set>
#include <thread>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/core/downsampler.h"
#include "services/core/feature_space.h"
#include "services/core/kmeans.h"

namespace fleetmem::core {
namespace {

constexpr int kDim = 8;

// A robot's segment: `n` traces along a road, codes drawn around a few
// prototypes, random rewards.
std::vector<MemoryTrace> Segment(const std::string& robot, uint64_t first_seq,
                                 int n, std::mt19937_64& rng) {
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  std::uniform_real_distribution<float> reward(0.0f, 2.0f);
  std::vector<MemoryTrace> batch;
  for (int i = 0; i < n; ++i) {
    MemoryTrace t;
    t.robot_id = robot;
    t.seq = first_seq + i;
    t.domain = i % 3 == 0 ? "night" : "summer";
    t.code.resize(kDim);
    for (float& v : t.code) v = gauss(rng);
    t.place.x = 5.0 * i + gauss(rng);
    t.place.y = gauss(rng);
    t.reward = reward(rng);
    t.timestamp_ns = static_cast<int64_t>(t.seq) * 1000;
    t.encoder_version = "v1";
    batch.push_back(std::move(t));
  }
  return batch;
}

// A one-trace cluster at code `code` (and place 0), reward `reward`.
Cluster OneTraceCluster(uint64_t id, std::vector<float> code, float reward,
                        double spatial_scale_m) {
  MemoryTrace t;
  t.robot_id = "old";
  t.seq = id;
  t.code = std::move(code);
  t.reward = reward;
  t.cluster_id = id;
  Cluster c;
  c.id = id;
  c.robot_id = "old";
  const Eigen::VectorXf f = FeatureSpatialCode(t, spatial_scale_m);
  c.centroid.assign(f.data(), f.data() + f.size());
  c.traces.push_back(std::move(t));
  return c;
}

void ExpectInvariants(const StaticMemory& memory) {
  const MemoryOptions& o = memory.options();
  EXPECT_LE(memory.clusters().size(), static_cast<size_t>(o.max_clusters));
  size_t traces = 0;
  std::map<std::string, uint64_t, std::less<>> by_robot, by_domain;
  for (const auto& [id, cluster] : memory.clusters()) {
    EXPECT_EQ(cluster.id, id);
    for (const MemoryTrace& t : cluster.traces) {
      ++by_robot[t.robot_id];
      ++by_domain[t.domain];
    }
    if (o.clustering) {
      EXPECT_LE(cluster.traces.size(),
                static_cast<size_t>(o.max_traces_per_cluster));
    }
    EXPECT_FALSE(cluster.traces.empty());
    for (const MemoryTrace& t : cluster.traces) {
      EXPECT_EQ(t.cluster_id, id);
      EXPECT_EQ(memory.Find(t.key()), &t);
    }
    traces += cluster.traces.size();
  }
  EXPECT_EQ(memory.trace_count(), traces);
  // The incrementally kept counts equal a walk over every trace.
  EXPECT_EQ(memory.traces_by_robot(), by_robot);
  EXPECT_EQ(memory.traces_by_domain(), by_domain);
}

TEST(StaticMemoryTest, EmptyBatchChangesNothing) {
  StaticMemory memory(MemoryOptions{});
  std::mt19937_64 rng(1);
  const ConsolidationResult r = memory.Consolidate({}, 1, rng);
  EXPECT_TRUE(r.added.empty());
  EXPECT_TRUE(r.downsampled.empty());
  EXPECT_TRUE(r.forgotten.empty());
  EXPECT_TRUE(memory.clusters().empty());
}

TEST(StaticMemoryTest, ConsolidateClustersAndDownsamples) {
  MemoryOptions options;
  options.clusters_per_batch = 5;
  options.max_traces_per_cluster = 4;
  StaticMemory memory(options);
  std::mt19937_64 data_rng(3);
  const std::vector<MemoryTrace> batch = Segment("r1", 100, 60, data_rng);

  // The same k-means run the memory does, to check the downsampling.
  std::mt19937_64 rng(9);
  std::mt19937_64 rng_copy = rng;
  Eigen::MatrixXf points(kDim + 3, 60);
  for (int i = 0; i < 60; ++i) {
    points.col(i) = FeatureSpatialCode(batch[i], options.spatial_scale_m);
  }
  const KMeansResult kmeans =
      KMeans(points, 5, options.kmeans_max_iterations, rng_copy);

  const ConsolidationResult r = memory.Consolidate(batch, 40, rng);
  ASSERT_EQ(r.added.size(), 5u);
  EXPECT_TRUE(r.forgotten.empty());
  size_t kept = 0;
  for (size_t i = 0; i < r.added.size(); ++i) {
    const Cluster& c = r.added[i];
    EXPECT_EQ(c.id, 40 + i);
    EXPECT_EQ(c.robot_id, "r1");
    kept += c.traces.size();
    // Kept = the N_max highest rewards of k-means group i.
    std::vector<MemoryTrace> group;
    for (int p = 0; p < 60; ++p) {
      if (kmeans.assignment[p] == static_cast<int>(i))
        group.push_back(batch[p]);
    }
    DownsampleByReward(group, 4);
    std::set<uint64_t> want, got;
    for (const MemoryTrace& t : group) want.insert(t.seq);
    for (const MemoryTrace& t : c.traces) got.insert(t.seq);
    EXPECT_EQ(got, want) << "cluster " << c.id;
    // Centroid recomputed from the kept traces.
    Eigen::VectorXf mean = Eigen::VectorXf::Zero(kDim + 3);
    for (const MemoryTrace& t : c.traces) {
      mean += FeatureSpatialCode(t, options.spatial_scale_m);
    }
    mean /= static_cast<float>(c.traces.size());
    ASSERT_EQ(c.centroid.size(), static_cast<size_t>(kDim + 3));
    for (int d = 0; d < kDim + 3; ++d) {
      EXPECT_NEAR(c.centroid[d], mean[d], 1e-5);
    }
    // The memory holds the centroid once (forgetting's tracker): the held
    // cluster has none, and comes out whole.
    EXPECT_TRUE(memory.clusters().at(c.id).centroid.empty());
    const std::optional<Cluster> whole = memory.WithCentroid(c.id);
    ASSERT_TRUE(whole.has_value());
    EXPECT_EQ(whole->centroid, c.centroid);
    EXPECT_EQ(whole->traces.size(), c.traces.size());
  }
  EXPECT_FALSE(memory.WithCentroid(39).has_value());
  EXPECT_EQ(kept, 20u);
  EXPECT_EQ(r.downsampled.size(), 40u);
  EXPECT_EQ(memory.trace_count(), 20u);
  for (const MemoryTrace& t : r.downsampled) {
    EXPECT_EQ(memory.Find(t.key()), nullptr);
  }
  ExpectInvariants(memory);
}

TEST(StaticMemoryTest, ConsolidateIsReproducible) {
  MemoryOptions options;
  options.clusters_per_batch = 6;
  options.max_traces_per_cluster = 5;
  std::mt19937_64 data_rng(3);
  const std::vector<MemoryTrace> batch = Segment("r1", 0, 80, data_rng);
  StaticMemory a(options), b(options);
  std::mt19937_64 rng_a(5), rng_b(5);
  const ConsolidationResult ra = a.Consolidate(batch, 1, rng_a);
  const ConsolidationResult rb = b.Consolidate(batch, 1, rng_b);
  ASSERT_EQ(ra.added.size(), rb.added.size());
  for (size_t i = 0; i < ra.added.size(); ++i) {
    EXPECT_EQ(ra.added[i].centroid, rb.added[i].centroid);
    ASSERT_EQ(ra.added[i].traces.size(), rb.added[i].traces.size());
    for (size_t j = 0; j < ra.added[i].traces.size(); ++j) {
      EXPECT_EQ(ra.added[i].traces[j].key(), rb.added[i].traces[j].key());
    }
  }
}

// A plan made apart from the memory (as the engine makes it outside the
// fleet's lock) consolidates exactly as Consolidate with the same
// randomness does, forgetting included.
TEST(StaticMemoryTest, APlanMadeApartConsolidatesTheSame) {
  MemoryOptions options;
  options.clusters_per_batch = 6;
  options.max_traces_per_cluster = 5;
  options.max_clusters = 20;
  StaticMemory direct(options), planned(options);
  std::mt19937_64 data_rng(7), rng_direct(9), rng_planned(9);
  uint64_t next_cluster = 1;
  for (int b = 0; b < 12; ++b) {
    const std::vector<MemoryTrace> batch =
        Segment("r" + std::to_string(b % 3), 100 * b, 40, data_rng);
    const ConsolidationResult a =
        direct.Consolidate(batch, next_cluster, rng_direct);
    const ConsolidationPlan plan =
        PlanConsolidation(options, batch, rng_planned);
    ASSERT_EQ(plan.keys.size(), batch.size());
    const ConsolidationResult p =
        planned.Consolidate(batch, next_cluster, plan);
    ASSERT_EQ(a.added.size(), p.added.size());
    for (size_t i = 0; i < a.added.size(); ++i) {
      EXPECT_EQ(a.added[i].id, p.added[i].id);
      EXPECT_EQ(a.added[i].centroid, p.added[i].centroid);
      ASSERT_EQ(a.added[i].traces.size(), p.added[i].traces.size());
      for (size_t j = 0; j < a.added[i].traces.size(); ++j) {
        EXPECT_EQ(a.added[i].traces[j].key(), p.added[i].traces[j].key());
        EXPECT_EQ(p.added[i].traces[j].cluster_id, p.added[i].id);
      }
    }
    ASSERT_EQ(a.downsampled.size(), p.downsampled.size());
    for (size_t i = 0; i < a.downsampled.size(); ++i) {
      EXPECT_EQ(a.downsampled[i].key(), p.downsampled[i].key());
    }
    ASSERT_EQ(a.forgotten.size(), p.forgotten.size());
    for (size_t i = 0; i < a.forgotten.size(); ++i) {
      EXPECT_EQ(a.forgotten[i].id, p.forgotten[i].id);
    }
    next_cluster += a.added.size();
    ExpectInvariants(planned);
  }
  EXPECT_EQ(rng_direct(), rng_planned());
  EXPECT_EQ(direct.trace_count(), planned.trace_count());
}

TEST(StaticMemoryTest, SmallBatchGetsOneClusterPerTrace) {
  StaticMemory memory(MemoryOptions{});  // K = 20
  std::mt19937_64 rng(3);
  const ConsolidationResult r =
      memory.Consolidate(Segment("r1", 0, 7, rng), 1, rng);
  ASSERT_EQ(r.added.size(), 7u);
  for (const Cluster& c : r.added) EXPECT_EQ(c.traces.size(), 1u);
  ExpectInvariants(memory);
}

class BoundsTest : public ::testing::TestWithParam<bool> {};

TEST_P(BoundsTest, BoundsHoldOverManyBatches) {
  MemoryOptions options;
  options.clusters_per_batch = 8;
  options.max_traces_per_cluster = 5;
  options.max_clusters = 30;
  options.merge_on_forget = GetParam();
  StaticMemory memory(options);
  std::mt19937_64 rng(21);
  uint64_t next_cluster = 1;
  size_t added = 0, removed = 0;
  std::set<uint64_t> removed_ids;
  for (int b = 0; b < 40; ++b) {
    const std::string robot = "r" + std::to_string(b % 4);
    const ConsolidationResult r = memory.Consolidate(
        Segment(robot, 1000 * b, 50, rng), next_cluster, rng);
    ASSERT_EQ(r.added.size(), 8u);
    next_cluster += r.added.size();
    added += r.added.size();
    removed += r.forgotten.size() + r.merged.size();
    EXPECT_TRUE(options.merge_on_forget ? r.forgotten.empty()
                                        : r.merged.empty());
    for (const Cluster& c : r.forgotten) {
      EXPECT_TRUE(removed_ids.insert(c.id).second);
      EXPECT_FALSE(memory.clusters().contains(c.id));
      for (const MemoryTrace& t : c.traces) {
        EXPECT_EQ(memory.Find(t.key()), nullptr);
      }
    }
    for (const ClusterMerge& m : r.merged) {
      EXPECT_TRUE(removed_ids.insert(m.from.id).second);
      EXPECT_FALSE(memory.clusters().contains(m.from.id));
      for (const MemoryTrace& t : m.dropped) {
        EXPECT_EQ(memory.Find(t.key()), nullptr);
        EXPECT_EQ(t.cluster_id, 0u);
      }
    }
    for (uint64_t id : r.changed) EXPECT_TRUE(memory.clusters().contains(id));
    ASSERT_LE(memory.clusters().size(), 30u) << "batch " << b;
    ExpectInvariants(memory);
    if (HasFailure()) return;
  }
  EXPECT_EQ(memory.clusters().size(), 30u);
  EXPECT_EQ(added - removed, 30u);
}

INSTANTIATE_TEST_SUITE_P(DropAndMerge, BoundsTest, ::testing::Bool());

// Merging (the default): the survivor of the closest pair is the one the
// paper's forgetting keeps, and it takes the other's traces.
TEST(StaticMemoryTest, ForgettingMergesTheClosestPairIntoItsSurvivor) {
  MemoryOptions options;
  options.max_clusters = 2;
  StaticMemory memory(options);
  const double s = options.spatial_scale_m;
  memory.Restore(OneTraceCluster(1, {1, 0, 0, 0}, 5.0f, s));
  memory.Restore(OneTraceCluster(2, {0, 0, 0, 1}, 1.0f, s));
  const std::vector<float> centroid1 = memory.WithCentroid(1)->centroid;
  MemoryTrace near1;
  near1.robot_id = "r";
  near1.seq = 10;
  near1.code = {1, 0.1f, 0, 0};
  near1.reward = 2.0f;
  near1.domain = "winter";
  std::mt19937_64 rng(1);
  const ConsolidationResult r = memory.Consolidate({near1}, 3, rng);
  ASSERT_EQ(r.added.size(), 1u);
  EXPECT_TRUE(r.forgotten.empty());
  ASSERT_EQ(r.merged.size(), 1u);
  EXPECT_EQ(r.merged[0].from.id, 3u);  // lower mean reward than cluster 1
  EXPECT_EQ(r.merged[0].into, 1u);
  EXPECT_TRUE(r.merged[0].dropped.empty());
  EXPECT_EQ(r.merged[0].from.centroid, r.added[0].centroid);
  EXPECT_EQ(r.changed, std::vector<uint64_t>{1});
  // Cluster 1 holds both traces, and its centroid is the mean of the two.
  const std::optional<Cluster> one = memory.WithCentroid(1);
  ASSERT_TRUE(one.has_value());
  ASSERT_EQ(one->traces.size(), 2u);
  const MemoryTrace* moved = memory.Find(near1.key());
  ASSERT_NE(moved, nullptr);
  EXPECT_EQ(moved->cluster_id, 1u);
  ASSERT_EQ(one->centroid.size(), centroid1.size());
  for (size_t d = 0; d < centroid1.size(); ++d) {
    EXPECT_FLOAT_EQ(one->centroid[d],
                    (centroid1[d] + r.added[0].centroid[d]) / 2.0f)
        << d;
  }
  EXPECT_EQ(memory.trace_count(), 3u);
  EXPECT_EQ(memory.traces_by_domain().at("winter"), 1u);
  ExpectInvariants(memory);
}

// A merge that does not fit N_max keeps traces spread over the places, and
// every domain of the two clusters.
TEST(StaticMemoryTest, AMergeThatOverflowsKeepsPlacesAndDomains) {
  MemoryOptions options;
  options.max_clusters = 1;
  options.max_traces_per_cluster = 4;
  options.clusters_per_batch = 1;
  options.spatial_scale_m = 1e6;  // places barely move the centroids
  StaticMemory memory(options);
  auto batch = [](const std::string& domain, uint64_t first_seq) {
    std::vector<MemoryTrace> traces;
    for (int i = 0; i < 4; ++i) {
      MemoryTrace t;
      t.robot_id = "r";
      t.seq = first_seq + static_cast<uint64_t>(i);
      t.domain = domain;
      t.code = {1, 0, 0};
      t.place.x = 10.0 * i;  // 0, 10, 20, 30 m
      t.reward = 1.0f + 0.1f * static_cast<float>(i);
      traces.push_back(std::move(t));
    }
    return traces;
  };
  std::mt19937_64 rng(3);
  memory.Consolidate(batch("summer", 0), 1, rng);
  const ConsolidationResult r =
      memory.Consolidate(batch("winter", 100), 2, rng);
  ASSERT_EQ(r.merged.size(), 1u);
  ASSERT_EQ(r.merged[0].dropped.size(), 4u);
  ASSERT_EQ(memory.clusters().size(), 1u);
  const Cluster& kept = memory.clusters().begin()->second;
  // Both seasons keep the two ends of the stretch (farthest points).
  std::set<std::pair<std::string, double>> held;
  for (const MemoryTrace& t : kept.traces) held.insert({t.domain, t.place.x});
  EXPECT_EQ(held, (std::set<std::pair<std::string, double>>{{"summer", 0.0},
                                                            {"summer", 30.0},
                                                            {"winter", 0.0},
                                                            {"winter", 30.0}}));
  ExpectInvariants(memory);
}

TEST(StaticMemoryTest, ForgettingRemovesLowerRewardOfClosestPair) {
  MemoryOptions options;
  options.max_clusters = 2;
  options.merge_on_forget = false;  // the paper's Algorithm 2
  StaticMemory memory(options);
  const double s = options.spatial_scale_m;
  // Cluster 1 (reward 5) and cluster 2 (reward 1) are far apart.
  memory.Restore(OneTraceCluster(1, {1, 0, 0, 0}, 5.0f, s));
  memory.Restore(OneTraceCluster(2, {0, 0, 0, 1}, 1.0f, s));
  EXPECT_EQ(memory.trace_count(), 2u);

  // A new trace close to cluster 1 with a lower reward: it is forgotten.
  MemoryTrace near1;
  near1.robot_id = "r";
  near1.seq = 10;
  near1.code = {1, 0.1f, 0, 0};
  near1.reward = 2.0f;
  std::mt19937_64 rng(1);
  ConsolidationResult r = memory.Consolidate({near1}, 3, rng);
  ASSERT_EQ(r.added.size(), 1u);
  ASSERT_EQ(r.forgotten.size(), 1u);
  EXPECT_EQ(r.forgotten[0].id, 3u);
  EXPECT_EQ(r.added[0].id, 3u);  // reported as added and forgotten
  // A forgotten cluster comes out whole, centroid included.
  EXPECT_EQ(r.forgotten[0].centroid, r.added[0].centroid);
  EXPECT_FALSE(r.forgotten[0].centroid.empty());
  EXPECT_EQ(memory.Find(near1.key()), nullptr);

  // A new trace close to cluster 1 with a higher reward: cluster 1 goes.
  near1.seq = 11;
  near1.reward = 9.0f;
  r = memory.Consolidate({near1}, 4, rng);
  ASSERT_EQ(r.forgotten.size(), 1u);
  EXPECT_EQ(r.forgotten[0].id, 1u);
  EXPECT_THAT(memory.clusters(), ::testing::SizeIs(2));
  EXPECT_TRUE(memory.clusters().contains(2));
  EXPECT_TRUE(memory.clusters().contains(4));
  EXPECT_NE(memory.Find(near1.key()), nullptr);

  // Equal mean rewards: the older cluster (smaller id) goes.
  MemoryTrace near2;
  near2.robot_id = "r";
  near2.seq = 12;
  near2.code = {0, 0, 0.1f, 1};
  near2.reward = 1.0f;
  r = memory.Consolidate({near2}, 5, rng);
  ASSERT_EQ(r.forgotten.size(), 1u);
  EXPECT_EQ(r.forgotten[0].id, 2u);
  ExpectInvariants(memory);
}

TEST(StaticMemoryTest, RestoredClustersTakePartInForgetting) {
  MemoryOptions options;
  options.max_clusters = 3;
  options.merge_on_forget = false;
  StaticMemory memory(options);
  const double s = options.spatial_scale_m;
  memory.Restore(OneTraceCluster(1, {1, 0, 0}, 1.0f, s));
  memory.Restore(OneTraceCluster(2, {1, 0.01f, 0}, 0.5f, s));  // near 1
  memory.Restore(OneTraceCluster(3, {0, 0, 1}, 1.0f, s));
  EXPECT_EQ(memory.clusters().size(), 3u);
  MemoryTrace far;
  far.robot_id = "r";
  far.seq = 1;
  far.code = {0, 1, 0};
  far.reward = 1.0f;
  std::mt19937_64 rng(1);
  const ConsolidationResult r = memory.Consolidate({far}, 4, rng);
  ASSERT_EQ(r.forgotten.size(), 1u);
  EXPECT_EQ(r.forgotten[0].id, 2u);
}

TEST(StaticMemoryTest, WithoutClusteringTheBatchIsOneCluster) {
  MemoryOptions options;
  options.clustering = false;
  options.max_traces_per_cluster = 5;
  StaticMemory memory(options);
  std::mt19937_64 rng(3);
  const std::vector<MemoryTrace> batch = Segment("r9", 0, 40, rng);
  const ConsolidationResult r = memory.Consolidate(batch, 7, rng);
  ASSERT_EQ(r.added.size(), 1u);
  EXPECT_TRUE(r.downsampled.empty());
  EXPECT_EQ(r.added[0].id, 7u);
  EXPECT_EQ(r.added[0].robot_id, "r9");
  EXPECT_EQ(r.added[0].traces.size(), 40u);
  EXPECT_EQ(memory.trace_count(), 40u);
  for (const MemoryTrace& t : batch) {
    const MemoryTrace* found = memory.Find(t.key());
    ASSERT_NE(found, nullptr);
    EXPECT_EQ(found->cluster_id, 7u);
  }
}

TEST(StaticMemoryTest, SampleForReplayIncrementsCounts) {
  MemoryOptions options;
  options.clustering = false;
  StaticMemory memory(options);
  std::mt19937_64 rng(3);
  memory.Consolidate(Segment("r1", 0, 30, rng), 1, rng);

  const std::vector<MemoryTrace> drawn = memory.SampleForReplay(10, rng);
  ASSERT_EQ(drawn.size(), 10u);
  std::set<TraceKey> keys;
  for (const MemoryTrace& t : drawn) {
    EXPECT_TRUE(keys.insert(t.key()).second) << "duplicate";
    EXPECT_EQ(t.replay_count, 1u);
    EXPECT_EQ(memory.Find(t.key())->replay_count, 1u);
  }
  size_t replayed = 0;
  for (const MemoryTrace& t : memory.clusters().begin()->second.traces) {
    replayed += t.replay_count;
  }
  EXPECT_EQ(replayed, 10u);

  const std::vector<MemoryTrace> all = memory.SampleForReplay(1000, rng);
  EXPECT_EQ(all.size(), 30u);  // clamped
  for (const MemoryTrace& t : all) {
    EXPECT_EQ(t.replay_count, keys.contains(t.key()) ? 2u : 1u);
  }
  EXPECT_TRUE(memory.SampleForReplay(0, rng).empty());
}

// The pair-keeping refresh (refresh_pair_radius): a summer and a winter
// segment over the same 30 places; both draws (embedded and distributed
// mode's) hand out anchors each followed by the other season's trace of
// its place, replay counts following; Eq. 18's draw pairs by chance only.
TEST(StaticMemoryTest, ThePairKeepingRefreshHandsOutPlacesInBothDomains) {
  auto seasons = [](std::mt19937_64& rng) {
    std::vector<MemoryTrace> batch = Segment("r1", 0, 30, rng);
    std::vector<MemoryTrace> winter = Segment("r2", 0, 30, rng);
    for (int i = 0; i < 30; ++i) {
      batch[i].domain = "summer";
      batch[i].place = {.x = 10.0 * i};
      winter[i].domain = "winter";
      winter[i].place = {.x = 10.0 * i + 1.0};
    }
    batch.insert(batch.end(), winter.begin(), winter.end());
    return batch;
  };
  MemoryOptions options;
  options.clustering = false;
  options.refresh_pair_radius = 3.0;
  ASSERT_TRUE(ValidateMemoryOptions(options).ok());
  for (const bool in_memory_order : {false, true}) {
    StaticMemory memory(options);
    std::mt19937_64 rng(11);
    memory.Consolidate(seasons(rng), 1, rng);
    const std::vector<MemoryTrace> drawn =
        in_memory_order ? memory.SampleForReplayInMemoryOrder(20, rng)
                        : memory.SampleForReplay(20, rng);
    ASSERT_EQ(drawn.size(), 20u);
    std::set<TraceKey> keys;
    for (size_t i = 0; i < drawn.size(); i += 2) {
      EXPECT_NE(drawn[i].domain, drawn[i + 1].domain);
      EXPECT_NEAR(std::abs(drawn[i].place.x - drawn[i + 1].place.x), 1.0, 1e-9);
    }
    for (const MemoryTrace& t : drawn) {
      EXPECT_TRUE(keys.insert(t.key()).second);
      EXPECT_EQ(t.replay_count, 1u);
      EXPECT_EQ(memory.Find(t.key())->replay_count, 1u);
    }
  }
  options.refresh_pair_radius = -1.0;
  EXPECT_FALSE(ValidateMemoryOptions(options).ok());
}

// refresh_uniform: a trace of reward 1e6 beside 19 of reward 1e-3 is drawn
// first nearly always by Eq. 18's weights, about once in 20 uniformly.
TEST(StaticMemoryTest, TheUniformRefreshIgnoresTheWeights) {
  auto heavy_first = [](bool uniform, bool in_memory_order) {
    MemoryOptions options;
    options.clustering = false;
    options.refresh_uniform = uniform;
    int first = 0;
    for (uint64_t seed = 1; seed <= 200; ++seed) {
      StaticMemory memory(options);
      std::mt19937_64 rng(seed);
      std::vector<MemoryTrace> batch = Segment("r1", 0, 20, rng);
      for (MemoryTrace& t : batch) t.reward = t.seq == 7 ? 1e6f : 1e-3f;
      memory.Consolidate(batch, 1, rng);
      const std::vector<MemoryTrace> drawn =
          in_memory_order ? memory.SampleForReplayInMemoryOrder(1, rng)
                          : memory.SampleForReplay(1, rng);
      first += drawn.at(0).seq == 7 ? 1 : 0;
    }
    return first;
  };
  for (const bool in_memory_order : {false, true}) {
    EXPECT_GE(heavy_first(false, in_memory_order), 195);
    EXPECT_LE(heavy_first(true, in_memory_order), 30);  // mean 10
  }
}

// Distributed mode's draw: a memory restored from another's clusters (its
// sampler slots in another order once forgetting freed and reused some)
// draws what the original draws from an equal generator.
TEST(StaticMemoryTest, InMemoryOrderDrawsDependOnlyOnWhatIsHeld) {
  MemoryOptions options;
  options.clusters_per_batch = 4;
  options.max_traces_per_cluster = 3;
  options.max_clusters = 5;
  StaticMemory live(options);
  std::mt19937_64 rng(5);
  uint64_t next_id = 1;
  for (uint64_t first = 0; first < 120; first += 20) {
    ConsolidationResult result =
        live.Consolidate(Segment("r1", first, 20, rng), next_id, rng);
    next_id += result.added.size();
  }
  ASSERT_FALSE(live.SampleForReplay(4, rng).empty());  // counts differ
  StaticMemory restored(options);
  for (const auto& [id, cluster] : live.clusters()) {
    restored.Restore(*live.WithCentroid(id));
  }
  for (uint64_t seed = 1; seed <= 5; ++seed) {
    std::mt19937_64 a(seed), b(seed);
    const std::vector<MemoryTrace> from_live =
        live.SampleForReplayInMemoryOrder(6, a);
    const std::vector<MemoryTrace> from_restored =
        restored.SampleForReplayInMemoryOrder(6, b);
    ASSERT_EQ(from_live.size(), 6u);
    ASSERT_EQ(from_live.size(), from_restored.size());
    for (size_t i = 0; i < from_live.size(); ++i) {
      EXPECT_EQ(from_live[i].key(), from_restored[i].key()) << seed;
      EXPECT_EQ(from_live[i].replay_count, from_restored[i].replay_count);
      EXPECT_EQ(live.Find(from_live[i].key())->replay_count,
                from_live[i].replay_count);
    }
  }
}

// First draw from a fresh memory of two equal-reward traces, one of which
// was replayed 20 times: decay makes it unlikely; gamma = 1 ignores n.
double ShareOfReplayedTraceDrawnFirst(double gamma) {
  MemoryOptions options;
  options.replay_decay = gamma;
  std::mt19937_64 rng(31);
  int replayed_first = 0;
  constexpr int kTrials = 4000;
  for (int t = 0; t < kTrials; ++t) {
    StaticMemory memory(options);
    Cluster c = OneTraceCluster(1, {1, 0}, 1.0f, options.spatial_scale_m);
    MemoryTrace second = c.traces[0];
    second.seq = 2;
    second.replay_count = 20;
    c.traces.push_back(second);
    memory.Restore(std::move(c));
    if (memory.SampleForReplay(1, rng)[0].seq == 2) ++replayed_first;
  }
  return static_cast<double>(replayed_first) / kTrials;
}

TEST(StaticMemoryTest, DecayLowersChanceOfReplayedTraces) {
  // 0.9^20 / (1 + 0.9^20) = 0.108.
  EXPECT_NEAR(ShareOfReplayedTraceDrawnFirst(0.9), 0.108, 0.03);
  EXPECT_NEAR(ShareOfReplayedTraceDrawnFirst(1.0), 0.5, 0.03);
}

// A memory restored with its saved centroid bookkeeping forgets as the
// memory it was saved from; another memory's bookkeeping is refused and
// rebuilt, and the memory is complete either way.
TEST(StaticMemoryTest, RestoreAllUsesSavedCentroidsOnlyWhenTheyMatch) {
  MemoryOptions options;
  options.clusters_per_batch = 8;
  options.max_traces_per_cluster = 5;
  options.max_clusters = 40;
  options.forgetting_exact_below = 16;  // the centroid graph is in use
  StaticMemory memory(options);
  std::mt19937_64 rng(33);
  uint64_t next_cluster = 1;
  for (int b = 0; b < 12; ++b) {
    next_cluster +=
        memory.Consolidate(Segment("r1", 1000 * b, 50, rng), next_cluster, rng)
            .added.size();
  }
  std::string bytes;
  ByteWriter out([&bytes](std::span<const char> data) {
    bytes.append(data.data(), data.size());
  });
  memory.SaveCentroids(out);
  auto copies = [&] {
    std::vector<Cluster> clusters;
    for (const auto& [id, cluster] : memory.clusters()) {
      clusters.push_back(cluster);
    }
    return clusters;
  };

  StaticMemory restored(options);
  ByteReader in(bytes);
  ASSERT_TRUE(restored.RestoreAll(copies(), in).ok());
  EXPECT_EQ(restored.trace_count(), memory.trace_count());
  ExpectInvariants(restored);
  // The same next consolidations forget the same clusters.
  std::mt19937_64 rng_a(35), rng_b(35);
  for (int b = 12; b < 16; ++b) {
    std::mt19937_64 segment_rng(b);
    const std::vector<MemoryTrace> segment =
        Segment("r2", 1000 * b, 50, segment_rng);
    const ConsolidationResult a =
        memory.Consolidate(segment, next_cluster, rng_a);
    const ConsolidationResult c =
        restored.Consolidate(segment, next_cluster, rng_b);
    next_cluster += a.added.size();
    ASSERT_EQ(a.forgotten.size(), c.forgotten.size());
    for (size_t i = 0; i < a.forgotten.size(); ++i) {
      EXPECT_EQ(a.forgotten[i].id, c.forgotten[i].id);
    }
  }

  // Damaged bookkeeping: refused, rebuilt, memory complete.
  StaticMemory other(options);
  std::vector<Cluster> clusters = copies();
  ByteReader damaged(std::span<const char>(bytes).first(bytes.size() / 2));
  const absl::Status status = other.RestoreAll(clusters, damaged);
  EXPECT_EQ(status.code(), absl::StatusCode::kDataLoss) << status;
  EXPECT_EQ(other.clusters().size(), clusters.size());
  ExpectInvariants(other);
}

// Bookkeeping saved at an earlier state of the memory (a periodic snapshot
// before a crash) is reconciled with the clusters made and forgotten since:
// with exact neighbours the restored memory then forgets exactly as the
// memory that never stopped; with the centroid graph it forgets only
// clusters it holds and keeps its bounds.
TEST(StaticMemoryTest, RestoreAllReconcilesCentroidsSavedEarlier) {
  for (const size_t exact_below : {size_t{1000}, size_t{16}}) {
    SCOPED_TRACE(exact_below);
    MemoryOptions options;
    options.clusters_per_batch = 8;
    options.max_traces_per_cluster = 5;
    options.max_clusters = 40;
    options.forgetting_exact_below = exact_below;
    StaticMemory memory(options);
    std::mt19937_64 rng(33);
    uint64_t next_cluster = 1;
    std::string earlier;
    ByteWriter out([&earlier](std::span<const char> data) {
      earlier.append(data.data(), data.size());
    });
    for (int b = 0; b < 12; ++b) {
      // Saved after 8 segments; 4 more add and forget 32 clusters.
      if (b == 8) memory.SaveCentroids(out);
      next_cluster +=
          memory
              .Consolidate(Segment("r1", 1000 * b, 50, rng), next_cluster, rng)
              .added.size();
    }
    std::vector<Cluster> clusters;
    for (const auto& [id, cluster] : memory.clusters()) {
      clusters.push_back(cluster);
    }
    StaticMemory restored(options);
    ByteReader in(earlier);
    size_t reconciled = 0;
    ASSERT_TRUE(restored.RestoreAll(clusters, in, &reconciled).ok());
    EXPECT_GT(reconciled, 0u);  // clusters made and forgotten since
    ExpectInvariants(restored);
    std::mt19937_64 rng_a(35), rng_b(35);
    for (int b = 12; b < 16; ++b) {
      std::mt19937_64 segment_rng(b);
      const std::vector<MemoryTrace> segment =
          Segment("r2", 1000 * b, 50, segment_rng);
      std::set<uint64_t> held;
      for (const auto& [id, cluster] : restored.clusters()) held.insert(id);
      const ConsolidationResult a =
          memory.Consolidate(segment, next_cluster, rng_a);
      const ConsolidationResult c =
          restored.Consolidate(segment, next_cluster, rng_b);
      for (const Cluster& cluster : c.added) held.insert(cluster.id);
      next_cluster += a.added.size();
      ASSERT_EQ(a.forgotten.size(), c.forgotten.size());
      for (size_t i = 0; i < c.forgotten.size(); ++i) {
        EXPECT_TRUE(held.erase(c.forgotten[i].id)) << c.forgotten[i].id;
        if (exact_below == 1000) {
          EXPECT_EQ(a.forgotten[i].id, c.forgotten[i].id);
        }
      }
      ExpectInvariants(restored);
    }
  }
}

// An empty memory's restore in two halves (RunBoth) gives the memory that
// one thread restores, whichever half runs first and when they run at
// once: every trace found in its cluster, the same counts, the same draws
// from equal generators. A restore the halves would not fit (a used
// memory, ids out of order) is done on one thread.
TEST(StaticMemoryTest, RestoreAllInTwoHalvesRestoresWhatOneThreadDoes) {
  MemoryOptions options;
  options.clusters_per_batch = 6;
  options.max_traces_per_cluster = 5;
  options.max_clusters = 60;
  options.merge_on_forget = true;  // clusters that mix robots
  StaticMemory memory(options);
  std::mt19937_64 rng(41);
  uint64_t next_cluster = 1;
  for (int b = 0; b < 15; ++b) {
    const std::string robot = absl::StrCat("robot-", b % 3);
    next_cluster +=
        memory.Consolidate(Segment(robot, 1000 * b, 40, rng), next_cluster, rng)
            .added.size();
  }
  std::string bytes;
  ByteWriter out([&bytes](std::span<const char> data) {
    bytes.append(data.data(), data.size());
  });
  memory.SaveCentroids(out);
  std::vector<Cluster> clusters;
  for (const auto& [id, cluster] : memory.clusters()) {
    clusters.push_back(*memory.WithCentroid(id));
  }

  int calls = 0;
  const RunBoth second_first = [&calls](const std::function<void()>& first,
                                        const std::function<void()>& second) {
    ++calls;
    second();
    first();
  };
  const RunBoth at_once = [&calls](const std::function<void()>& first,
                                   const std::function<void()>& second) {
    ++calls;
    std::thread thread(second);
    first();
    thread.join();
  };
  auto restore = [&](std::vector<Cluster> restored_clusters,
                     const RunBoth& run_both) {
    auto restored = std::make_unique<StaticMemory>(options);
    ByteReader in(bytes);
    size_t reconciled = 99;
    EXPECT_TRUE(restored
                    ->RestoreAll(std::move(restored_clusters), in, &reconciled,
                                 run_both)
                    .ok());
    EXPECT_EQ(reconciled, 0u);
    return restored;
  };
  auto draws = [](StaticMemory& restored) {
    std::mt19937_64 draw_rng(7);
    std::vector<TraceKey> keys;
    for (const MemoryTrace& trace : restored.SampleForReplay(100, draw_rng)) {
      keys.push_back(trace.key());
    }
    return keys;
  };
  const std::unique_ptr<StaticMemory> one = restore(clusters, nullptr);
  ExpectInvariants(*one);
  ASSERT_EQ(one->trace_count(), memory.trace_count());
  const std::vector<TraceKey> one_draws = draws(*one);
  for (const RunBoth* run_both : {&second_first, &at_once}) {
    calls = 0;
    const std::unique_ptr<StaticMemory> two = restore(clusters, *run_both);
    EXPECT_EQ(calls, 1);
    ExpectInvariants(*two);
    EXPECT_EQ(two->trace_count(), one->trace_count());
    EXPECT_EQ(two->traces_by_robot(), one->traces_by_robot());
    EXPECT_EQ(draws(*two), one_draws);
  }

  // Ids out of order: one thread, the same memory.
  calls = 0;
  std::vector<Cluster> reversed(clusters.rbegin(), clusters.rend());
  const std::unique_ptr<StaticMemory> from_reversed =
      restore(reversed, second_first);
  EXPECT_EQ(calls, 0);
  ExpectInvariants(*from_reversed);
  EXPECT_EQ(from_reversed->trace_count(), one->trace_count());
  // A used memory: one thread (and the saved centroids refused).
  StaticMemory used(options);
  used.Restore(clusters.front());
  ByteReader in(bytes);
  const absl::Status status = used.RestoreAll(
      std::vector<Cluster>(clusters.begin() + 1, clusters.end()), in, nullptr,
      second_first);
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition) << status;
  EXPECT_EQ(calls, 0);
  ExpectInvariants(used);
  EXPECT_EQ(used.trace_count(), one->trace_count());
}

}  // namespace
}  // namespace fleetmem::core

namespace fleetmem::core {
namespace {

std::vector<TraceKey> KeysOf(const std::vector<MemoryTrace>& traces,
                             const std::string& robot) {
  std::vector<TraceKey> keys;
  for (const MemoryTrace& t : traces) {
    if (t.robot_id == robot) keys.push_back(t.key());
  }
  return keys;
}

TEST(StaticMemoryTest, RemovedTracesLeaveAndTheirClustersFollow) {
  MemoryOptions options;
  options.clusters_per_batch = 4;
  StaticMemory memory(options);
  std::mt19937_64 rng(5);
  memory.Consolidate(Segment("a", 1, 40, rng), 1, rng);
  memory.Consolidate(Segment("b", 1, 40, rng), 5, rng);
  // Robot a's codes, by key, for the centroids' recomputation; one of them
  // dropped by the memory as the engine's index keeps it.
  std::map<TraceKey, std::vector<float>> codes;
  std::vector<MemoryTrace> held;
  for (const auto& [id, cluster] : memory.clusters()) {
    for (const MemoryTrace& t : cluster.traces) {
      codes[t.key()] = t.code;
      held.push_back(t);
    }
  }
  const size_t before = memory.trace_count();
  // Half of b's traces and every one of a's, and a key never held.
  std::vector<TraceKey> leaving = KeysOf(held, "a");
  std::vector<TraceKey> of_b = KeysOf(held, "b");
  leaving.insert(leaving.end(), of_b.begin(), of_b.begin() + of_b.size() / 2);
  leaving.push_back(TraceKey{"nobody", 3});
  ASSERT_TRUE(memory.DropCode(of_b.back()));
  const RemovalResult removal = memory.Remove(
      leaving, [&](const MemoryTrace& t) { return codes.at(t.key()); });

  EXPECT_EQ(removal.removed.size(), leaving.size() - 1);
  EXPECT_EQ(memory.trace_count(), before - removal.removed.size());
  for (const TraceKey& key : leaving) EXPECT_EQ(memory.Find(key), nullptr);
  EXPECT_FALSE(memory.traces_by_robot().contains("a"));
  ExpectInvariants(memory);
  // a's clusters held only a's traces: they left whole.
  for (const Cluster& emptied : removal.emptied) {
    EXPECT_EQ(memory.clusters().count(emptied.id), 0u);
    EXPECT_FALSE(emptied.centroid.empty());
  }
  EXPECT_GE(removal.emptied.size(), 1u);
  // A changed cluster's centroid is the mean of what it keeps.
  for (const Cluster& changed : removal.changed) {
    Eigen::VectorXd sum = Eigen::VectorXd::Zero(kDim + 3);
    for (const MemoryTrace& t : changed.traces) {
      MemoryTrace probe = t;
      probe.code = codes.at(t.key());
      sum += FeatureSpatialCode(probe, options.spatial_scale_m).cast<double>();
    }
    sum /= static_cast<double>(changed.traces.size());
    ASSERT_EQ(changed.centroid.size(), static_cast<size_t>(kDim + 3));
    for (int d = 0; d < kDim + 3; ++d) {
      EXPECT_NEAR(changed.centroid[d], sum[d], 1e-5);
    }
    EXPECT_EQ(memory.WithCentroid(changed.id)->centroid, changed.centroid);
  }
  // Removing again changes nothing; replay draws only what is held.
  EXPECT_TRUE(memory.Remove(leaving, nullptr).removed.empty());
  const std::vector<MemoryTrace> drawn = memory.SampleForReplay(1000, rng);
  EXPECT_EQ(drawn.size(), memory.trace_count());
  for (const MemoryTrace& t : drawn) EXPECT_EQ(t.robot_id, "b");
  // Forgetting still works on what is left.
  memory.Consolidate(Segment("c", 1, 40, rng), 9, rng);
  ExpectInvariants(memory);
}

TEST(StaticMemoryTest, ANewRewardChangesTheReplayWeight) {
  MemoryOptions options;
  options.replay_decay = 1.0;
  StaticMemory memory(options);
  for (uint64_t id = 1; id <= 2; ++id) {
    memory.Restore(OneTraceCluster(id, std::vector<float>(kDim, id), 1.0f,
                                   options.spatial_scale_m));
  }
  // Trace ("old", 2) gets almost all the weight: drawn first nearly always.
  ASSERT_TRUE(memory.SetReward(TraceKey{"old", 2}, 900.0f, 99.0f));
  EXPECT_FALSE(memory.SetReward(TraceKey{"old", 7}, 1.0f, 1.0f));
  const MemoryTrace* rescored = memory.Find(TraceKey{"old", 2});
  EXPECT_FLOAT_EQ(rescored->reward, 999.0f);
  EXPECT_FLOAT_EQ(rescored->reward_external, 900.0f);
  EXPECT_FLOAT_EQ(rescored->reward_internal, 99.0f);
  int first = 0;
  for (int trial = 0; trial < 200; ++trial) {
    StaticMemory copy(options);
    for (const auto& [id, cluster] : memory.clusters()) {
      copy.Restore(*memory.WithCentroid(id));
    }
    std::mt19937_64 rng(trial);
    if (copy.SampleForReplay(1, rng)[0].seq == 2) ++first;
  }
  EXPECT_GE(first, 195);
}

}  // namespace
}  // namespace fleetmem::core
