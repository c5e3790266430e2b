#include "services/core/memory_options.h"

#include <cmath>
#include <functional>
#include <limits>
#include <string>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

using ::testing::HasSubstr;

TEST(ValidateMemoryOptionsTest, DefaultsAreValid) {
  EXPECT_TRUE(ValidateMemoryOptions(MemoryOptions{}).ok());
}

TEST(ValidateMemoryOptionsTest, BoundaryValuesAreValid) {
  MemoryOptions options;
  options.clusters_per_batch = 1;
  options.max_traces_per_cluster = 1;
  options.max_clusters = 1;
  options.replay_decay = 0.0;
  options.kmeans_max_iterations = 1;
  EXPECT_TRUE(ValidateMemoryOptions(options).ok());
  options.replay_decay = 1.0;
  EXPECT_TRUE(ValidateMemoryOptions(options).ok());
}

struct BadOption {
  std::string field;
  std::function<void(MemoryOptions&)> set;
};

TEST(ValidateMemoryOptionsTest, RejectsOutOfRangeNamingTheField) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  const BadOption cases[] = {
      {"clusters_per_batch",
       [](MemoryOptions& o) { o.clusters_per_batch = 0; }},
      {"max_traces_per_cluster",
       [](MemoryOptions& o) { o.max_traces_per_cluster = -1; }},
      {"max_clusters", [](MemoryOptions& o) { o.max_clusters = 0; }},
      {"replay_decay", [](MemoryOptions& o) { o.replay_decay = -0.1; }},
      {"replay_decay", [](MemoryOptions& o) { o.replay_decay = 1.5; }},
      {"replay_decay", [nan](MemoryOptions& o) { o.replay_decay = nan; }},
      {"reward_floor", [](MemoryOptions& o) { o.reward_floor = 0.0; }},
      {"reward_floor", [nan](MemoryOptions& o) { o.reward_floor = nan; }},
      {"spatial_scale_m", [](MemoryOptions& o) { o.spatial_scale_m = -3.0; }},
      {"spatial_scale_m", [inf](MemoryOptions& o) { o.spatial_scale_m = inf; }},
      {"kmeans_max_iterations",
       [](MemoryOptions& o) { o.kmeans_max_iterations = 0; }},
  };
  for (const BadOption& c : cases) {
    MemoryOptions options;
    c.set(options);
    const absl::Status status = ValidateMemoryOptions(options);
    EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << c.field;
    EXPECT_THAT(std::string(status.message()), HasSubstr(c.field));
  }
}

}  // namespace
}  // namespace fleetmem::core
