#include "services/core/trace_filter.h"

#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

MemoryTrace Trace(std::string robot, uint64_t seq, std::string domain,
                  int64_t t) {
  MemoryTrace trace;
  trace.robot_id = std::move(robot);
  trace.seq = seq;
  trace.domain = std::move(domain);
  trace.timestamp_ns = t;
  return trace;
}

TEST(TraceFilterTest, ATraceMatchesWhenItMeetsEveryCriterionSet) {
  TraceFilter all;
  EXPECT_TRUE(all.selects_all());
  EXPECT_TRUE(all.Matches(Trace("a", 1, "summer", 5)));

  TraceFilter filter;
  filter.robot_id = "a";
  filter.domain = "winter";
  filter.seq_first = 10;
  filter.seq_last = 20;
  filter.time_from_ns = 100;
  filter.time_to_ns = 200;
  EXPECT_FALSE(filter.selects_all());
  EXPECT_TRUE(filter.Matches(Trace("a", 10, "winter", 100)));
  EXPECT_TRUE(filter.Matches(Trace("a", 20, "winter", 199)));
  EXPECT_FALSE(filter.Matches(Trace("b", 15, "winter", 150)));
  EXPECT_FALSE(filter.Matches(Trace("a", 15, "summer", 150)));
  EXPECT_FALSE(filter.Matches(Trace("a", 9, "winter", 150)));
  EXPECT_FALSE(filter.Matches(Trace("a", 21, "winter", 150)));
  EXPECT_FALSE(filter.Matches(Trace("a", 15, "winter", 99)));
  EXPECT_FALSE(filter.Matches(Trace("a", 15, "winter", 200)));  // exclusive
}

TEST(TraceFilterTest, MalformedFiltersAreRefusedNamingTheField) {
  TraceFilter seqs_without_robot;
  seqs_without_robot.seq_first = 3;
  EXPECT_TRUE(absl::IsInvalidArgument(
      ValidateTraceFilter("selector", seqs_without_robot)));
  TraceFilter backwards;
  backwards.robot_id = "a";
  backwards.seq_first = 5;
  backwards.seq_last = 4;
  EXPECT_TRUE(
      absl::IsInvalidArgument(ValidateTraceFilter("selector", backwards)));
  TraceFilter empty_time;
  empty_time.time_from_ns = 7;
  empty_time.time_to_ns = 7;
  EXPECT_TRUE(
      absl::IsInvalidArgument(ValidateTraceFilter("selector", empty_time)));
  TraceFilter bad_robot;
  bad_robot.robot_id = "a b";
  const absl::Status status = ValidateTraceFilter("selector", bad_robot);
  EXPECT_TRUE(absl::IsInvalidArgument(status));
  EXPECT_NE(status.message().find("selector.robot_id"), std::string::npos)
      << status;
  TraceFilter fine;
  fine.robot_id = "a";
  fine.seq_first = 4;
  fine.seq_last = 4;
  EXPECT_TRUE(ValidateTraceFilter("selector", fine).ok());
}

}  // namespace
}  // namespace fleetmem::core
