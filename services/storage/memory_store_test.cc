// Conformance tests of engine::MemoryStore, run against both stores.
#include "services/engine/memory_store.h"

#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/storage/in_memory_store.h"
#include "services/storage/rocksdb_store.h"
#include "services/storage/testing/store_test_util.h"

namespace fleetmem::storage {
namespace {

using core::EventType;
using engine::FleetMutation;
using engine::FleetRecord;
using testing::Dump;
using testing::MakeCluster;
using testing::MakeEvent;
using testing::MakeMeta;
using testing::MakeRobot;
using testing::MakeTrace;

enum class StoreKind { kInMemory, kRocksDb };

std::string KindName(StoreKind kind) {
  return kind == StoreKind::kInMemory ? "InMemory" : "RocksDb";
}

void PrintTo(StoreKind kind, std::ostream* os) { *os << KindName(kind); }

// One store under test; Reopen() closes and reopens a RocksDB store on the
// same directory (the in-memory store stays as it is).
class StoreHarness {
 public:
  explicit StoreHarness(StoreKind kind) : kind_(kind) { Reopen(); }

  engine::MemoryStore& store() { return *store_; }

  void Reopen() {
    if (kind_ == StoreKind::kInMemory) {
      if (store_ == nullptr) store_ = NewInMemoryStore();
      return;
    }
    store_.reset();
    RocksDbStoreOptions options;
    options.path = absl::StrCat(dir_.path(), "/db");
    absl::StatusOr<std::unique_ptr<engine::MemoryStore>> store =
        OpenRocksDbStore(options);
    ASSERT_TRUE(store.ok()) << store.status();
    store_ = std::move(*store);
  }

 private:
  StoreKind kind_;
  testing::TempDir dir_;
  std::unique_ptr<engine::MemoryStore> store_;
};

FleetRecord Load(engine::MemoryStore& store, std::string_view fleet_id) {
  absl::StatusOr<FleetRecord> record = store.LoadFleet(fleet_id);
  EXPECT_TRUE(record.ok()) << record.status();
  return record.ok() ? std::move(*record) : FleetRecord{};
}

std::vector<core::MemoryEvent> Events(engine::MemoryStore& store,
                                      std::string_view fleet_id, uint64_t after,
                                      size_t limit) {
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      store.ReadEvents(fleet_id, after, limit);
  EXPECT_TRUE(events.ok()) << events.status();
  return events.ok() ? std::move(*events) : std::vector<core::MemoryEvent>{};
}

std::vector<std::string> Fleets(engine::MemoryStore& store) {
  absl::StatusOr<std::vector<std::string>> fleets = store.ListFleets();
  EXPECT_TRUE(fleets.ok()) << fleets.status();
  return fleets.ok() ? std::move(*fleets) : std::vector<std::string>{};
}

// ---------------------------------------------------------------------------
// Round trips: mutations applied to fleet "f", then the record that
// LoadFleet must return, before and after reopening.

struct RoundTripCase {
  std::string name;
  std::vector<FleetMutation> mutations;
  FleetRecord want;
};

void PrintTo(const RoundTripCase& c, std::ostream* os) { *os << c.name; }

FleetRecord Want() {
  FleetRecord record;
  record.fleet_id = "f";
  return record;
}

std::vector<RoundTripCase> RoundTripCases() {
  std::vector<RoundTripCase> cases;
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "Meta";
    FleetMutation& m = c.mutations.emplace_back();
    m.put_meta = true;
    m.meta = MakeMeta(7);
    c.want = Want();
    c.want.meta = MakeMeta(7);
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "PendingPutOverwriteErase";
    FleetMutation& put = c.mutations.emplace_back();
    put.put_pending = {MakeTrace("r1", 3), MakeTrace("r0", 7),
                       MakeTrace("r1", 1), MakeTrace("r10", 2),
                       MakeTrace("r1", 256)};
    FleetMutation& change = c.mutations.emplace_back();
    core::MemoryTrace changed = MakeTrace("r1", 3);
    changed.reward = 9.5f;
    changed.code = {1.0f, 2.0f};
    change.put_pending = {changed};
    change.erase_pending = {{"r0", 7}, {"r0", 8}, {"nobody", 1}};
    c.want = Want();
    c.want.pending = {MakeTrace("r1", 1), changed, MakeTrace("r1", 256),
                      MakeTrace("r10", 2)};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "EraseThenPutInOneMutation";
    c.mutations.emplace_back().put_pending = {MakeTrace("r", 1)};
    FleetMutation& m = c.mutations.emplace_back();
    core::MemoryTrace again = MakeTrace("r", 1);
    again.domain = "again";
    m.erase_pending = {{"r", 1}};
    m.put_pending = {again};
    c.want = Want();
    c.want.pending = {again};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "ClustersByIdTracesInGivenOrder";
    core::Cluster seven = MakeCluster(7, "r1", {5, 2, 9});
    core::Cluster three = MakeCluster(3, "r2", {1, 4});
    core::Cluster sent = seven;
    sent.traces[1].cluster_id = 0;  // the store sets it
    c.mutations.emplace_back().put_clusters = {sent, three};
    c.want = Want();
    c.want.clusters = {three, seven};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "EraseClusterErasesItsTraces";
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {1, 2}),
                                               MakeCluster(2, "r", {3})};
    c.mutations.emplace_back().erase_clusters = {1, 99};
    // The id comes back with other traces: none of the old ones may reappear.
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {100})};
    c.want = Want();
    c.want.clusters = {MakeCluster(1, "r", {100}), MakeCluster(2, "r", {3})};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "PutClusterReplacesItsMembers";
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {1, 2, 3})};
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {3, 4})};
    // Erasing a trace that was dropped is a no-op, not a corruption.
    c.mutations.emplace_back().erase_traces = {{"r", 1}};
    c.want = Want();
    c.want.clusters = {MakeCluster(1, "r", {3, 4})};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "TraceMovesBetweenClusters";
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {1, 2})};
    c.mutations.emplace_back().put_clusters = {MakeCluster(2, "r", {2, 3})};
    // Cluster 1 no longer owns r/2: erasing it must leave r/2 in cluster 2.
    c.mutations.emplace_back().erase_clusters = {1};
    c.want = Want();
    c.want.clusters = {MakeCluster(2, "r", {2, 3})};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "EraseAndPutClusterInOneMutation";  // erasures come first
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {1, 2})};
    FleetMutation& m = c.mutations.emplace_back();
    m.erase_clusters = {1};
    m.put_clusters = {MakeCluster(1, "r", {2, 3})};
    c.want = Want();
    c.want.clusters = {MakeCluster(1, "r", {2, 3})};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "UpdateTracesKeepsClusterIgnoresUnknown";
    c.mutations.emplace_back().put_clusters = {MakeCluster(4, "r", {1, 2})};
    core::MemoryTrace replayed = MakeTrace("r", 2);  // cluster_id 0
    replayed.replay_count = 5;
    FleetMutation& m = c.mutations.emplace_back();
    m.update_traces = {replayed, MakeTrace("r", 99)};
    replayed.replay_count = 6;
    c.mutations.emplace_back().update_traces = {replayed};
    c.want = Want();
    core::Cluster want = MakeCluster(4, "r", {1, 2});
    want.traces[1].replay_count = 6;
    c.want.clusters = {want};
  }
  {
    // A replay draw's update (FleetMutation::update_traces_held): the
    // engine names each trace's cluster, and the store writes it unread.
    RoundTripCase& c = cases.emplace_back();
    c.name = "UpdateTracesHeldByTheEngine";
    c.mutations.emplace_back().put_clusters = {MakeCluster(4, "r", {1, 2})};
    core::MemoryTrace replayed = MakeCluster(4, "r", {1, 2}).traces[1];
    replayed.replay_count = 7;
    FleetMutation& m = c.mutations.emplace_back();
    m.update_traces = {replayed};
    m.update_traces_held = true;
    c.want = Want();
    core::Cluster want = MakeCluster(4, "r", {1, 2});
    want.traces[1].replay_count = 7;
    c.want.clusters = {want};
  }
  {
    // A merge as the engine writes it: the survivor takes the traces of a
    // cluster erased in the same mutation, none with its code (the store
    // keeps what it holds; FleetMutation::put_clusters).
    RoundTripCase& c = cases.emplace_back();
    c.name = "MergeWithoutCodesKeepsTheStoredOnes";
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {1, 2}),
                                               MakeCluster(2, "r", {3, 4})};
    core::Cluster merged = MakeCluster(1, "r", {1, 2, 3});
    merged.centroid = {0.5f, 0.25f};
    merged.traces[0].replay_count = 4;
    core::Cluster sent = merged;
    for (core::MemoryTrace& trace : sent.traces) trace.code.clear();
    FleetMutation& m = c.mutations.emplace_back();
    m.erase_clusters = {2};
    m.put_clusters = {sent};
    c.want = Want();
    c.want.clusters = {merged};
  }
  {
    // A trace moved between two put clusters without its code, the
    // cluster it leaves put first, then last.
    RoundTripCase& c = cases.emplace_back();
    c.name = "TraceMovesWithoutItsCode";
    c.mutations.emplace_back().put_clusters = {MakeCluster(1, "r", {1, 2}),
                                               MakeCluster(2, "r", {3})};
    auto codeless = [](core::Cluster cluster) {
      for (core::MemoryTrace& trace : cluster.traces) trace.code.clear();
      return cluster;
    };
    c.mutations.emplace_back().put_clusters = {
        codeless(MakeCluster(1, "r", {1})),
        codeless(MakeCluster(2, "r", {3, 2}))};
    c.mutations.emplace_back().put_clusters = {
        codeless(MakeCluster(2, "r", {3})),
        codeless(MakeCluster(1, "r", {1, 2}))};
    c.mutations.emplace_back().put_clusters = {
        codeless(MakeCluster(2, "r", {3, 2})),
        codeless(MakeCluster(1, "r", {1}))};
    c.want = Want();
    c.want.clusters = {MakeCluster(1, "r", {1}), MakeCluster(2, "r", {3, 2})};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "UpdateWithoutCodeKeepsTheStoredOne";
    c.mutations.emplace_back().put_clusters = {MakeCluster(4, "r", {1, 2})};
    core::MemoryTrace rewarded = MakeCluster(4, "r", {1, 2}).traces[1];
    rewarded.reward = 3.5f;
    rewarded.code.clear();
    c.mutations.emplace_back().update_traces = {rewarded};
    c.want = Want();
    core::Cluster want = MakeCluster(4, "r", {1, 2});
    want.traces[1].reward = 3.5f;
    c.want.clusters = {want};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "EraseSingleTraces";
    c.mutations.emplace_back().put_clusters = {MakeCluster(4, "r", {1, 2, 3}),
                                               MakeCluster(5, "q", {1})};
    c.mutations.emplace_back().erase_traces = {{"r", 2}, {"r", 50}, {"q", 1}};
    c.want = Want();
    c.want.clusters = {MakeCluster(4, "r", {1, 3}), MakeCluster(5, "q", {})};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "RobotsSeqSetIntervals";
    c.mutations.emplace_back().put_robots = {
        MakeRobot("r2", {{1, 5}, {7, 7}, {10, 20}}, 42), MakeRobot("r1", {}, 0),
        MakeRobot("r10", {{3, 3}, {UINT64_MAX - 1, UINT64_MAX}}, 1)};
    c.mutations.emplace_back().put_robots = {MakeRobot("r1", {{1, 1}}, 8)};
    c.want = Want();
    c.want.robots = {
        MakeRobot("r1", {{1, 1}}, 8),
        MakeRobot("r10", {{3, 3}, {UINT64_MAX - 1, UINT64_MAX}}, 1),
        MakeRobot("r2", {{1, 5}, {7, 7}, {10, 20}}, 42)};
  }
  {
    RoundTripCase& c = cases.emplace_back();
    c.name = "ConsolidationInOneMutation";
    c.mutations.emplace_back().put_pending = {
        MakeTrace("r", 1), MakeTrace("r", 2), MakeTrace("r", 3)};
    FleetMutation& m = c.mutations.emplace_back();
    m.put_meta = true;
    m.meta = MakeMeta(1);
    m.erase_pending = {{"r", 1}, {"r", 2}};
    m.put_clusters = {MakeCluster(1, "r", {2, 1})};
    m.put_robots = {MakeRobot("r", {{1, 3}}, 0)};
    m.append_events = {MakeEvent(1, EventType::kClusterAdded, 1)};
    c.want = Want();
    c.want.meta = MakeMeta(1);
    c.want.pending = {MakeTrace("r", 3)};
    c.want.clusters = {MakeCluster(1, "r", {2, 1})};
    c.want.robots = {MakeRobot("r", {{1, 3}}, 0)};
  }
  return cases;
}

class RoundTripTest
    : public ::testing::TestWithParam<std::tuple<StoreKind, RoundTripCase>> {};

TEST_P(RoundTripTest, LoadReturnsWhatWasApplied) {
  const auto& [kind, c] = GetParam();
  StoreHarness harness(kind);
  for (const FleetMutation& m : c.mutations) {
    ASSERT_TRUE(harness.store().Apply("f", m).ok());
  }
  EXPECT_EQ(Dump(Load(harness.store(), "f")), Dump(c.want));
  harness.Reopen();
  EXPECT_EQ(Dump(Load(harness.store(), "f")), Dump(c.want)) << "after reopen";
  EXPECT_EQ(Fleets(harness.store()), std::vector<std::string>{"f"});
}

INSTANTIATE_TEST_SUITE_P(
    BothStores, RoundTripTest,
    ::testing::Combine(::testing::Values(StoreKind::kInMemory,
                                         StoreKind::kRocksDb),
                       ::testing::ValuesIn(RoundTripCases())),
    [](const auto& info) {
      return absl::StrCat(KindName(std::get<0>(info.param)), "_",
                          std::get<1>(info.param).name);
    });

// ---------------------------------------------------------------------------
// Behaviour beyond one fleet's record.

class StoreTest : public ::testing::TestWithParam<StoreKind> {
 protected:
  StoreTest() : harness_(GetParam()) {}
  engine::MemoryStore& store() { return harness_.store(); }

  StoreHarness harness_;
};

TEST_P(StoreTest, EmptyStore) {
  EXPECT_TRUE(Fleets(store()).empty());
  EXPECT_EQ(Dump(Load(store(), "nobody")), Dump([] {
              FleetRecord r;
              r.fleet_id = "nobody";
              return r;
            }()));
  EXPECT_TRUE(Events(store(), "nobody", 0, 10).empty());
}

// A restart with an index snapshot leaves out the codes the snapshot
// holds: only those, never a pending trace's; everything else as LoadFleet.
TEST_P(StoreTest, LoadWithoutHeldCodesLeavesOutOnlyThose) {
  FleetMutation m;
  m.put_meta = true;
  m.meta = MakeMeta(1);
  m.put_pending = {MakeTrace("r2", 9)};
  m.put_clusters = {MakeCluster(1, "r1", {3, 1}), MakeCluster(2, "r2", {4})};
  ASSERT_TRUE(store().Apply("f", m).ok());
  const FleetRecord full = Load(store(), "f");
  std::vector<std::string> asked;
  absl::StatusOr<FleetRecord> partial =
      store().LoadFleetWithoutHeldCodes("f", [&](const core::TraceKey& key) {
        asked.push_back(absl::StrCat(key.robot_id, "/", key.seq));
        return key.seq != 4;
      });
  ASSERT_TRUE(partial.ok()) << partial.status();
  EXPECT_THAT(asked, ::testing::UnorderedElementsAre("r1/1", "r1/3", "r2/4"));
  FleetRecord want = full;
  for (core::Cluster& cluster : want.clusters) {
    for (core::MemoryTrace& trace : cluster.traces) {
      if (trace.seq != 4) trace.code.clear();
    }
  }
  ASSERT_FALSE(want.pending.front().code.empty());
  EXPECT_EQ(Dump(*partial), Dump(want));
  // A null function keeps every code.
  absl::StatusOr<FleetRecord> all = store().LoadFleetWithoutHeldCodes("f", {});
  ASSERT_TRUE(all.ok());
  EXPECT_EQ(Dump(*all), Dump(full));
}

TEST_P(StoreTest, EventsAfterCursorWithLimit) {
  std::vector<core::MemoryEvent> all;
  for (uint64_t id = 1; id <= 300; ++id) {
    all.push_back(MakeEvent(
        id,
        id % 4 == 0 ? EventType::kClusterForgotten : EventType::kClusterAdded,
        id / 2));
    if (id % 7 == 0) {  // a merge, with its own fields
      all.back().type = EventType::kClusterMerged;
      all.back().merged_into = id + 1;
      all.back().traces_dropped = static_cast<uint32_t>(id % 5);
    }
  }
  FleetMutation first;
  first.append_events.assign(all.begin(), all.begin() + 200);
  FleetMutation second;
  second.append_events.assign(all.begin() + 200, all.end());
  ASSERT_TRUE(store().Apply("f", first).ok());
  ASSERT_TRUE(store().Apply("f", second).ok());
  FleetMutation other;  // another fleet's events stay out of f's stream
  other.append_events = {MakeEvent(301, EventType::kClusterAdded, 1)};
  ASSERT_TRUE(store().Apply("f1", other).ok());

  auto slice = [&](size_t begin, size_t end) {
    return std::vector<core::MemoryEvent>(all.begin() + begin,
                                          all.begin() + end);
  };
  struct Case {
    uint64_t after;
    size_t limit;
    std::vector<core::MemoryEvent> want;
  };
  const std::vector<Case> cases = {
      {0, 1000, all},
      {0, 3, slice(0, 3)},
      {3, 4, slice(3, 7)},
      {255, 2, slice(255, 257)},  // crosses a byte
      {298, 10, slice(298, 300)},
      {300, 10, {}},
      {5, 0, {}},
      {UINT64_MAX, 10, {}},
  };
  for (const Case& c : cases) {
    EXPECT_EQ(Dump(Events(store(), "f", c.after, c.limit)), Dump(c.want))
        << "after " << c.after << " limit " << c.limit;
  }
  harness_.Reopen();
  EXPECT_EQ(Dump(Events(store(), "f", 100, 1000)), Dump(slice(100, 300)));
  EXPECT_EQ(Dump(Events(store(), "f1", 0, 1000)), Dump(other.append_events));
}

TEST_P(StoreTest, EventRetentionErasesOlderEvents) {
  FleetMutation first;
  for (uint64_t id = 1; id <= 300; ++id) {
    first.append_events.push_back(MakeEvent(id, EventType::kClusterAdded, id));
  }
  ASSERT_TRUE(store().Apply("f", first).ok());
  FleetMutation other;
  other.append_events = {MakeEvent(1, EventType::kClusterAdded, 1)};
  ASSERT_TRUE(store().Apply("f1", other).ok());
  FleetMutation trim;  // one more event, and only the newest 100 kept
  trim.append_events = {MakeEvent(301, EventType::kClusterAdded, 301)};
  trim.erase_events_before = 202;
  ASSERT_TRUE(store().Apply("f", trim).ok());
  for (bool reopened : {false, true}) {
    if (reopened) harness_.Reopen();
    const std::vector<core::MemoryEvent> kept = Events(store(), "f", 0, 1000);
    ASSERT_EQ(kept.size(), 100u) << "reopened " << reopened;
    EXPECT_EQ(kept.front().id, 202u);
    EXPECT_EQ(kept.back().id, 301u);
    EXPECT_EQ(Events(store(), "f1", 0, 10).size(), 1u)
        << "another fleet's events were erased";
  }
}

TEST_P(StoreTest, FleetsAreIsolated) {
  // "f" is a byte prefix of the others: their keys must never mix.
  const std::vector<std::string> fleets = {"f", "f1", "f.1", "g"};
  for (size_t i = 0; i < fleets.size(); ++i) {
    FleetMutation m;
    m.put_meta = true;
    m.meta = MakeMeta(i);
    m.put_pending = {MakeTrace("r", i + 1)};
    m.put_clusters = {MakeCluster(1, "r", {100 + i})};
    m.put_robots = {MakeRobot("r", {{1, i + 1}}, i)};
    m.append_events = {MakeEvent(1, EventType::kClusterAdded, 1)};
    ASSERT_TRUE(store().Apply(fleets[i], m).ok());
  }
  // Erasing everything of "f" leaves the others whole.
  FleetMutation erase;
  erase.erase_pending = {{"r", 1}, {"r", 2}, {"r", 3}};
  erase.erase_clusters = {1};
  ASSERT_TRUE(store().Apply("f", erase).ok());

  for (int reopen = 0; reopen < 2; ++reopen) {
    if (reopen) harness_.Reopen();
    for (size_t i = 0; i < fleets.size(); ++i) {
      FleetRecord want;
      want.fleet_id = fleets[i];
      want.meta = MakeMeta(i);
      if (i > 0) {
        want.pending = {MakeTrace("r", i + 1)};
        want.clusters = {MakeCluster(1, "r", {100 + i})};
      }
      want.robots = {MakeRobot("r", {{1, i + 1}}, i)};
      EXPECT_EQ(Dump(Load(store(), fleets[i])), Dump(want));
      EXPECT_EQ(Events(store(), fleets[i], 0, 10).size(), 1u) << fleets[i];
    }
    EXPECT_EQ(Fleets(store()),
              (std::vector<std::string>{"f", "f.1", "f1", "g"}));
  }
}

TEST_P(StoreTest, ListFleetsListsEveryFleetWithARecord) {
  FleetMutation pending_only;
  pending_only.put_pending = {MakeTrace("r", 1)};
  FleetMutation meta_only;
  meta_only.put_meta = true;
  FleetMutation events_only;
  events_only.append_events = {MakeEvent(4, EventType::kClusterAdded, 1)};
  ASSERT_TRUE(store().Apply("b", meta_only).ok());
  ASSERT_TRUE(store().Apply("a", pending_only).ok());
  ASSERT_TRUE(store().Apply("c", events_only).ok());
  ASSERT_TRUE(store().Apply("d", FleetMutation{}).ok());  // stores nothing
  EXPECT_EQ(Fleets(store()), (std::vector<std::string>{"a", "b", "c"}));

  FleetMutation erase;
  erase.erase_pending = {{"r", 1}};
  ASSERT_TRUE(store().Apply("a", erase).ok());
  harness_.Reopen();
  EXPECT_EQ(Fleets(store()), (std::vector<std::string>{"b", "c"}));
}

TEST_P(StoreTest, InvalidMutationsChangeNothing) {
  struct Case {
    std::string name;
    std::string fleet_id;
    FleetMutation mutation;
  };
  std::vector<Case> cases;
  auto add = [&](std::string name, std::string fleet_id) -> FleetMutation& {
    Case& c = cases.emplace_back();
    c.name = std::move(name);
    c.fleet_id = std::move(fleet_id);
    // A valid change that must not be applied along with the invalid one.
    c.mutation.put_pending = {MakeTrace("ok", 1)};
    return c.mutation;
  };
  add("empty fleet", "");
  add("NUL in fleet", std::string("f\0x", 3));
  add("NUL in robot", "f")
      .put_pending.push_back(MakeTrace(std::string("r\0", 2), 2));
  add("NUL in erased key", "f").erase_traces = {{std::string("\0", 1), 1}};
  add("cluster id 0", "f").put_clusters = {MakeCluster(0, "r", {1})};
  add("cluster twice", "f").put_clusters = {MakeCluster(2, "r", {1}),
                                            MakeCluster(2, "r", {2})};
  add("trace in two clusters", "f").put_clusters = {MakeCluster(2, "r", {1}),
                                                    MakeCluster(3, "r", {1})};
  core::MemoryTrace codeless = MakeTrace("r", 3);
  codeless.code.clear();
  add("pending trace without code", "f").put_pending.push_back(codeless);
  // No code stored for it either (the store is empty).
  core::Cluster codeless_cluster = MakeCluster(4, "r", {1, 2});
  codeless_cluster.traces[1].code.clear();
  add("clustered trace without code", "f").put_clusters = {codeless_cluster};
  add("event id 0", "f").append_events = {
      MakeEvent(0, EventType::kClusterAdded, 1)};
  for (const Case& c : cases) {
    EXPECT_EQ(store().Apply(c.fleet_id, c.mutation).code(),
              absl::StatusCode::kInvalidArgument)
        << c.name;
  }
  EXPECT_TRUE(Fleets(store()).empty());
  EXPECT_EQ(store().LoadFleet("").status().code(),
            absl::StatusCode::kInvalidArgument);
}

// A put cluster's trace without a code takes the stored one, and a
// pending trace's code is not one: the write is refused whole.
TEST_P(StoreTest, ClusteredTraceWithoutAStoredCodeChangesNothing) {
  FleetMutation upload;
  upload.put_pending = {MakeTrace("r", 5)};
  upload.put_clusters = {MakeCluster(1, "r", {1})};
  ASSERT_TRUE(store().Apply("f", upload).ok());
  const std::string before = Dump(Load(store(), "f"));

  core::Cluster consolidated = MakeCluster(2, "r", {5, 1});
  consolidated.traces[0].code.clear();  // pending: its code is not stored
  consolidated.traces[1].code.clear();  // stored: would be kept
  FleetMutation m;
  m.put_meta = true;
  m.meta = MakeMeta(3);
  m.erase_pending = {{"r", 5}};
  m.erase_clusters = {1};
  m.put_clusters = {consolidated};
  const absl::Status status = store().Apply("f", m);
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument) << status;
  EXPECT_THAT(std::string(status.message()),
              ::testing::HasSubstr("trace r/5 of cluster 2 comes without a "
                                   "code and none is stored for it"));
  EXPECT_EQ(Dump(Load(store(), "f")), before);
}

TEST_P(StoreTest, ScriptedWorkloadMatchesInMemoryReference) {
  const std::vector<FleetMutation> script = testing::ScriptedMutations(40);
  std::unique_ptr<engine::MemoryStore> reference = NewInMemoryStore();
  for (const FleetMutation& m : script) {
    ASSERT_TRUE(reference->Apply("fleet", m).ok());
  }
  // Four fleets written from four threads at once.
  std::vector<std::thread> writers;
  for (int t = 0; t < 4; ++t) {
    writers.emplace_back([&, t] {
      for (const FleetMutation& m : script) {
        EXPECT_TRUE(store().Apply(absl::StrCat("fleet", t), m).ok());
        EXPECT_TRUE(store().LoadFleet(absl::StrCat("fleet", t)).ok());
      }
    });
  }
  for (std::thread& writer : writers) writer.join();
  FleetRecord want = Load(*reference, "fleet");
  ASSERT_FALSE(want.clusters.empty());
  ASSERT_FALSE(want.pending.empty());
  const std::vector<core::MemoryEvent> want_events =
      Events(*reference, "fleet", 0, 1000);
  for (int t = 0; t < 4; ++t) {
    want.fleet_id = absl::StrCat("fleet", t);
    EXPECT_EQ(Dump(Load(store(), want.fleet_id)), Dump(want));
    EXPECT_EQ(Dump(Events(store(), want.fleet_id, 0, 1000)), Dump(want_events));
  }
}

// Writes `payload` as the fleet's index snapshot.
absl::Status SaveSnapshot(engine::MemoryStore& store, std::string_view fleet,
                          const std::string& payload) {
  return store.SaveIndexSnapshot(fleet, [&](core::ByteWriter& out) {
    out.PutBytes(payload.data(), payload.size());
    return absl::OkStatus();
  });
}

// The fleet's snapshot as a string, or the status of ReadIndexSnapshot.
absl::StatusOr<std::string> ReadSnapshot(engine::MemoryStore& store,
                                         std::string_view fleet) {
  std::string payload;
  absl::Status status = store.ReadIndexSnapshot(
      fleet, [&](const engine::IndexSnapshotBytes& snapshot) {
        payload.assign(snapshot.bytes.begin(), snapshot.bytes.end());
        return absl::OkStatus();
      });
  if (!status.ok()) return status;
  return payload;
}

TEST_P(StoreTest, IndexSnapshotIsKeptAcrossReadsAndReopens) {
  FleetMutation first;
  first.put_meta = true;
  first.meta = MakeMeta(1);
  ASSERT_TRUE(store().Apply("f1", first).ok());
  EXPECT_TRUE(absl::IsNotFound(ReadSnapshot(store(), "f1").status()));
  const std::string payload(3 << 20, 'x');  // several write buffers
  ASSERT_TRUE(SaveSnapshot(store(), "f1", payload).ok());
  ASSERT_TRUE(SaveSnapshot(store(), "f/2", "other fleet").ok());
  const std::string longest(128, 'z');  // core::kMaxIdLength
  ASSERT_TRUE(SaveSnapshot(store(), longest, "long id").ok());
  harness_.Reopen();
  absl::StatusOr<std::string> read = ReadSnapshot(store(), "f1");
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, payload);
  // Kept: a second start (a crash right after the first) reads it again.
  read = ReadSnapshot(store(), "f1");
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, payload);
  read = ReadSnapshot(store(), "f/2");
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, "other fleet");
  read = ReadSnapshot(store(), longest);
  ASSERT_TRUE(read.ok()) << read.status();
  EXPECT_EQ(*read, "long id");
  // A newer one replaces it.
  ASSERT_TRUE(SaveSnapshot(store(), "f1", "newer").ok());
  EXPECT_EQ(ReadSnapshot(store(), "f1").value_or(""), "newer");
}

// Writes after a snapshot leave it readable: the engine reconciles it with
// the stored state (traces added and removed since).
TEST_P(StoreTest, WritesAfterAnIndexSnapshotLeaveItReadable) {
  ASSERT_TRUE(SaveSnapshot(store(), "f1", "index").ok());
  FleetMutation other;
  other.put_pending.push_back(MakeTrace("r1", 1));
  ASSERT_TRUE(store().Apply("f1", other).ok());
  ASSERT_TRUE(store().Apply("f2", other).ok());
  harness_.Reopen();
  EXPECT_EQ(ReadSnapshot(store(), "f1").value_or(""), "index");
}

TEST_P(StoreTest, FailedIndexSnapshotWriteKeepsTheEarlierOne) {
  ASSERT_TRUE(SaveSnapshot(store(), "f1", "old").ok());
  absl::Status status =
      store().SaveIndexSnapshot("f1", [](core::ByteWriter& out) {
        out.Put<uint64_t>(7);
        return absl::InternalError("the index failed");
      });
  EXPECT_EQ(status.code(), absl::StatusCode::kInternal);
  EXPECT_EQ(ReadSnapshot(store(), "f1").value_or(""), "old");
  status = store().SaveIndexSnapshot("f2", [](core::ByteWriter& out) {
    return absl::InternalError("the index failed");
  });
  EXPECT_TRUE(absl::IsNotFound(ReadSnapshot(store(), "f2").status()));
  EXPECT_EQ(store().SaveIndexSnapshot("", nullptr).code(),
            absl::StatusCode::kInvalidArgument);
}

// `written` comes once the payload is complete and before it replaces the
// earlier snapshot (the engine lets its fleet change again there, while
// the file is synced); a failed write never calls it.
TEST_P(StoreTest, IndexSnapshotWrittenComesBeforeTheReplacement) {
  ASSERT_TRUE(SaveSnapshot(store(), "f1", "old").ok());
  int calls = 0;
  std::string seen;
  auto written = [&] {
    ++calls;
    seen = ReadSnapshot(store(), "f1").value_or("none");
  };
  ASSERT_TRUE(store()
                  .SaveIndexSnapshot(
                      "f1",
                      [](core::ByteWriter& out) {
                        out.PutBytes("new", 3);
                        return absl::OkStatus();
                      },
                      written)
                  .ok());
  EXPECT_EQ(calls, 1);
  EXPECT_EQ(seen, "old");
  EXPECT_EQ(ReadSnapshot(store(), "f1").value_or(""), "new");
  EXPECT_EQ(store()
                .SaveIndexSnapshot(
                    "f1",
                    [](core::ByteWriter&) {
                      return absl::InternalError("the index failed");
                    },
                    written)
                .code(),
            absl::StatusCode::kInternal);
  EXPECT_EQ(calls, 1);
}

// A snapshot saved after the fleet's last write describes the fleet
// exactly (the engine then takes its clusters from the snapshot): until the
// fleet's next write, whatever other fleets write, across a clean reopen.
// A refused write changes nothing, so leaves it current; a delete does not.
TEST_P(StoreTest, IndexSnapshotIsCurrentUntilTheFleetsNextWrite) {
  FleetMutation first;
  first.put_meta = true;
  first.meta = MakeMeta(1);
  first.put_pending = {MakeTrace("r1", 1)};
  ASSERT_TRUE(store().Apply("f1", first).ok());
  EXPECT_FALSE(store().IndexSnapshotCurrent("f1"));  // none saved
  ASSERT_TRUE(SaveSnapshot(store(), "f1", "index").ok());
  EXPECT_TRUE(store().IndexSnapshotCurrent("f1"));
  ASSERT_TRUE(store().Apply("f2", first).ok());
  ASSERT_TRUE(SaveSnapshot(store(), "f2", "other").ok());
  FleetMutation refused;
  refused.put_pending = {MakeTrace("r1", 2)};
  refused.put_pending.front().code.clear();
  ASSERT_FALSE(store().Apply("f1", refused).ok());
  EXPECT_TRUE(store().IndexSnapshotCurrent("f1"));
  harness_.Reopen();
  EXPECT_TRUE(store().IndexSnapshotCurrent("f1"));
  EXPECT_TRUE(store().IndexSnapshotCurrent("f2"));

  FleetMutation next;
  next.put_pending = {MakeTrace("r1", 3)};
  ASSERT_TRUE(store().Apply("f1", next).ok());
  EXPECT_FALSE(store().IndexSnapshotCurrent("f1"));
  EXPECT_TRUE(store().IndexSnapshotCurrent("f2"));
  EXPECT_EQ(ReadSnapshot(store(), "f1").value_or(""), "index");  // still read
  harness_.Reopen();
  EXPECT_FALSE(store().IndexSnapshotCurrent("f1"));
  ASSERT_TRUE(SaveSnapshot(store(), "f1", "newer").ok());
  EXPECT_TRUE(store().IndexSnapshotCurrent("f1"));

  engine::FleetMeta kept;
  kept.log_position = 9;
  ASSERT_TRUE(store().DeleteFleet("f1", kept).ok());
  EXPECT_FALSE(store().IndexSnapshotCurrent("f1"));
  EXPECT_TRUE(store().IndexSnapshotCurrent("f2"));
}

// The record without its clusters: meta, pending traces and robots as
// LoadFleet has them.
TEST_P(StoreTest, LoadWithoutClustersIsLoadFleetLessTheClusters) {
  FleetMutation m;
  m.put_meta = true;
  m.meta = MakeMeta(1);
  m.put_pending = {MakeTrace("r2", 9)};
  m.put_clusters = {MakeCluster(1, "r1", {3, 1}), MakeCluster(2, "r2", {4})};
  engine::RobotRecord robot;
  robot.robot_id = "r1";
  robot.replayed = 4;
  m.put_robots = {robot};
  ASSERT_TRUE(store().Apply("f", m).ok());
  FleetRecord want = Load(store(), "f");
  ASSERT_EQ(want.clusters.size(), 2u);
  want.clusters.clear();
  absl::StatusOr<FleetRecord> record = store().LoadFleetWithoutClusters("f");
  ASSERT_TRUE(record.ok()) << record.status();
  EXPECT_EQ(Dump(*record), Dump(want));
}

INSTANTIATE_TEST_SUITE_P(BothStores, StoreTest,
                         ::testing::Values(StoreKind::kInMemory,
                                           StoreKind::kRocksDb),
                         [](const auto& info) { return KindName(info.param); });

}  // namespace
}  // namespace fleetmem::storage
