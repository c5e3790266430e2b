#include "services/engine/upload_quota.h"

#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace fleetmem::engine {
namespace {

using ::testing::HasSubstr;

std::vector<core::MemoryTrace> Traces(const std::string& robot, size_t n,
                                      size_t dimension = 4) {
  std::vector<core::MemoryTrace> traces(n);
  for (size_t i = 0; i < n; ++i) {
    traces[i].robot_id = robot;
    traces[i].seq = i + 1;
    traces[i].code.assign(dimension, 1.0f);
  }
  return traces;
}

TEST(UploadQuotaTest, RobotRateRefillsOverTime) {
  double now = 100.0;
  QuotaOptions options;
  options.robot_traces_per_second = 10;  // bucket of 20 (burst 2 s)
  UploadQuota quota(options, [&] { return now; });
  EXPECT_TRUE(quota.AdmitRates("f", Traces("a", 20)).ok());
  const absl::Status refused = quota.AdmitRates("f", Traces("a", 5));
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.message(), HasSubstr("robot_traces_per_second"));
  EXPECT_THAT(refused.message(), HasSubstr("robot \"a\""));
  // Another robot has its own bucket.
  EXPECT_TRUE(quota.AdmitRates("f", Traces("b", 5)).ok());
  now += 0.5;  // 5 tokens back
  EXPECT_TRUE(quota.AdmitRates("f", Traces("a", 5)).ok());
  EXPECT_FALSE(quota.AdmitRates("f", Traces("a", 1)).ok());
  EXPECT_EQ(quota.Rejections("f").at("robot_traces_per_second"), 2u);
  EXPECT_TRUE(quota.Rejections("other").empty());
}

TEST(UploadQuotaTest, RefusedMessageConsumesNothing) {
  double now = 0.0;
  QuotaOptions options;
  options.fleet_traces_per_second = 100;  // bucket 200
  options.robot_traces_per_second = 5;    // bucket 10
  UploadQuota quota(options, [&] { return now; });
  EXPECT_TRUE(quota.AdmitRates("f", Traces("a", 10)).ok());
  // Robot "a" is out; the fleet bucket must not be charged for the refusal.
  for (int i = 0; i < 50; ++i) {
    EXPECT_FALSE(quota.AdmitRates("f", Traces("a", 10)).ok());
  }
  EXPECT_TRUE(quota.AdmitRates("f", Traces("b", 10)).ok());
}

TEST(UploadQuotaTest, BytesFleetsDimensionAndStored) {
  QuotaOptions options;
  options.fleet_bytes_per_second = 1000;
  options.max_fleets = 2;
  options.max_code_dimension = 8;
  options.max_traces_per_fleet = 100;
  UploadQuota quota(options, [] { return 0.0; });
  // A message larger than the bucket passes when the bucket is full ...
  EXPECT_TRUE(quota.AdmitRates("f", Traces("a", 100, 8)).ok());
  // ... and the next waits.
  EXPECT_THAT(quota.AdmitRates("f", Traces("a", 1, 8)).message(),
              HasSubstr("fleet_bytes_per_second"));
  EXPECT_TRUE(quota.AdmitNewFleet("g", 1).ok());
  EXPECT_THAT(quota.AdmitNewFleet("g", 2).message(), HasSubstr("max_fleets"));
  EXPECT_TRUE(quota.AdmitDimension("g", 8).ok());
  EXPECT_THAT(quota.AdmitDimension("g", 9).message(),
              HasSubstr("max_code_dimension"));
  EXPECT_TRUE(quota.AdmitStored("g", 90, 10).ok());
  EXPECT_THAT(quota.AdmitStored("g", 90, 11).message(),
              HasSubstr("max_traces_per_fleet"));
  EXPECT_EQ(quota.Rejections("g").size(), 3u);
}

TEST(UploadQuotaTest, OptionsAreValidated) {
  QuotaOptions options;
  options.robot_bytes_per_second = -1;
  EXPECT_FALSE(ValidateQuotaOptions(options).ok());
  options = QuotaOptions();
  options.burst_seconds = 0;
  EXPECT_FALSE(ValidateQuotaOptions(options).ok());
  EXPECT_TRUE(ValidateQuotaOptions(QuotaOptions()).ok());
}

}  // namespace
}  // namespace fleetmem::engine
