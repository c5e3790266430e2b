#include "services/engine/pending_traces.h"

#include <string>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::engine {
namespace {

core::MemoryTrace Trace(const std::string& robot, uint64_t seq,
                        const std::string& domain) {
  core::MemoryTrace trace;
  trace.robot_id = robot;
  trace.seq = seq;
  trace.domain = domain;
  trace.code = {static_cast<float>(seq)};
  return trace;
}

// The three views agree as traces come and robots' segments are taken:
// each robot's traces in arrival order, each trace by key, the counts per
// domain.
TEST(PendingTracesTest, TheViewsAgreeAsTracesComeAndGo) {
  PendingTraces pending;
  pending.Add(Trace("r1", 5, "summer"));
  pending.Add(Trace("r2", 1, "winter"));
  pending.Add(Trace("r1", 3, "winter"));
  EXPECT_EQ(pending.size(), 3u);
  ASSERT_EQ(pending.Of("r1").size(), 2u);
  EXPECT_EQ(pending.Of("r1")[1].seq, 3u);  // arrival order, not seq order
  EXPECT_TRUE(pending.Of("nobody").empty());
  const core::MemoryTrace* found = pending.Find({"r1", 3});
  ASSERT_NE(found, nullptr);
  EXPECT_EQ(found->code, std::vector<float>{3.0f});
  EXPECT_EQ(pending.Find({"r1", 4}), nullptr);
  EXPECT_EQ(pending.by_domain().at("winter"), 2u);

  std::vector<core::MemoryTrace> taken = pending.Take("r1");
  ASSERT_EQ(taken.size(), 2u);
  EXPECT_EQ(taken[0].seq, 5u);
  EXPECT_EQ(pending.size(), 1u);
  EXPECT_EQ(pending.Find({"r1", 5}), nullptr);
  EXPECT_EQ(pending.by_domain().count("summer"), 0u);  // none left: gone
  EXPECT_EQ(pending.by_domain().at("winter"), 1u);
  EXPECT_TRUE(pending.Take("r1").empty());
  EXPECT_EQ(pending.by_robot().size(), 1u);

  pending.Add(Trace("r1", 6, "summer"));  // a new segment starts
  EXPECT_EQ(pending.Find({"r1", 6})->seq, 6u);
  pending.Clear();
  EXPECT_TRUE(pending.empty());
  EXPECT_TRUE(pending.by_domain().empty());
  EXPECT_EQ(pending.Find({"r2", 1}), nullptr);
}

TEST(PendingTracesTest, RemovedAndRescoredTracesKeepTheViewsInStep) {
  PendingTraces pending;
  pending.Add(Trace("r1", 1, "summer"));
  pending.Add(Trace("r1", 2, "winter"));
  pending.Add(Trace("r1", 3, "summer"));
  pending.Add(Trace("r2", 1, "winter"));
  const std::vector<core::MemoryTrace> removed = pending.RemoveIf(
      [](const core::MemoryTrace& trace) { return trace.domain == "winter"; });
  ASSERT_EQ(removed.size(), 2u);
  EXPECT_EQ(pending.size(), 2u);
  EXPECT_EQ(pending.by_robot().count("r2"), 0u);  // left empty: gone
  EXPECT_EQ(pending.by_domain().count("winter"), 0u);
  ASSERT_EQ(pending.Of("r1").size(), 2u);
  EXPECT_EQ(pending.Of("r1")[1].seq, 3u);
  EXPECT_EQ(pending.Find({"r1", 3})->seq, 3u);  // positions follow
  EXPECT_EQ(pending.Find({"r1", 2}), nullptr);

  const core::MemoryTrace* rescored = pending.SetReward({"r1", 3}, 2.0f, 0.5f);
  ASSERT_NE(rescored, nullptr);
  EXPECT_FLOAT_EQ(pending.Find({"r1", 3})->reward, 2.5f);
  EXPECT_EQ(pending.SetReward({"r2", 1}, 1.0f, 1.0f), nullptr);
}

}  // namespace
}  // namespace fleetmem::engine
