#include "services/core/types.h"

#include <cmath>
#include <numbers>

#include "absl/container/flat_hash_map.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

MemoryTrace Trace(std::string domain, float reward, double x, double y) {
  MemoryTrace trace;
  trace.robot_id = "r1";
  trace.domain = std::move(domain);
  trace.reward = reward;
  trace.place.x = x;
  trace.place.y = y;
  return trace;
}

TEST(ClusterTest, MeanRewardOfEmptyClusterIsZero) {
  EXPECT_EQ(Cluster{}.MeanReward(), 0.0);
}

TEST(ClusterTest, MeanRewardAveragesTraces) {
  Cluster cluster;
  cluster.traces = {Trace("a", 1.0f, 0, 0), Trace("a", 2.0f, 0, 0),
                    Trace("a", 6.0f, 0, 0)};
  EXPECT_DOUBLE_EQ(cluster.MeanReward(), 3.0);
}

TEST(DescribeClusterTest, SummarisesCluster) {
  Cluster cluster;
  cluster.id = 7;
  cluster.robot_id = "robot-9";
  cluster.traces = {Trace("night", 1.0f, 0, 0), Trace("summer", 2.0f, 2, 4),
                    Trace("night", 3.0f, 4, 8)};
  const MemoryEvent event =
      DescribeCluster(cluster, EventType::kClusterForgotten);
  EXPECT_EQ(event.type, EventType::kClusterForgotten);
  EXPECT_EQ(event.cluster_id, 7u);
  EXPECT_EQ(event.trace_count, 3u);
  EXPECT_EQ(event.robot_id, "robot-9");
  EXPECT_EQ(event.domain, "night");
  EXPECT_DOUBLE_EQ(event.centroid_place.x, 2.0);
  EXPECT_DOUBLE_EQ(event.centroid_place.y, 4.0);
  EXPECT_FLOAT_EQ(event.mean_reward, 2.0f);
  EXPECT_EQ(event.id, 0u);  // left for the caller
  EXPECT_EQ(event.timestamp_ns, 0);
}

TEST(DescribeClusterTest, DomainTiesGoToSmallestName) {
  Cluster cluster;
  cluster.traces = {Trace("winter", 1, 0, 0), Trace("autumn", 1, 0, 0),
                    Trace("winter", 1, 0, 0), Trace("autumn", 1, 0, 0),
                    Trace("summer", 1, 0, 0)};
  EXPECT_EQ(DescribeCluster(cluster, EventType::kClusterAdded).domain,
            "autumn");
}

TEST(DescribeClusterTest, YawIsAveragedOnTheCircle) {
  Cluster cluster;
  cluster.traces = {Trace("a", 1, 0, 0), Trace("a", 1, 0, 0)};
  cluster.traces[0].place.yaw = std::numbers::pi - 0.1;
  cluster.traces[1].place.yaw = -std::numbers::pi + 0.1;
  const double yaw =
      DescribeCluster(cluster, EventType::kClusterAdded).centroid_place.yaw;
  EXPECT_NEAR(std::abs(yaw), std::numbers::pi, 1e-9);
}

TEST(DescribeClusterTest, EmptyCluster) {
  Cluster cluster;
  cluster.id = 3;
  const MemoryEvent event = DescribeCluster(cluster, EventType::kClusterAdded);
  EXPECT_EQ(event.trace_count, 0u);
  EXPECT_EQ(event.domain, "");
  EXPECT_EQ(event.mean_reward, 0.0f);
}

TEST(TraceKeyTest, OrdersAndHashes) {
  EXPECT_LT((TraceKey{"a", 9}), (TraceKey{"b", 1}));
  EXPECT_LT((TraceKey{"a", 1}), (TraceKey{"a", 2}));
  absl::flat_hash_map<TraceKey, int> map;
  map[TraceKey{"a", 1}] = 1;
  map[TraceKey{"a", 2}] = 2;
  MemoryTrace trace;
  trace.robot_id = "a";
  trace.seq = 2;
  EXPECT_EQ(map.at(trace.key()), 2);
}

}  // namespace
}  // namespace fleetmem::core
