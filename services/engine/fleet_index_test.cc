#include "services/engine/fleet_index.h"

#include <cmath>
#include <memory>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "services/core/byte_stream.h"
#include "services/index/exact_index.h"
#include "services/index/hnsw_index.h"

namespace fleetmem::engine {
namespace {

using core::MemoryTrace;
using core::TraceKey;

constexpr size_t kDimension = 8;

// A trace with a unit code of its own among the tests' traces: its largest
// component is at (3 seq + robot[0]) mod 8 (the index takes normalised
// codes).
MemoryTrace Trace(const std::string& robot, uint64_t seq) {
  MemoryTrace trace;
  trace.robot_id = robot;
  trace.seq = seq;
  trace.code.assign(kDimension, 0.0f);
  const size_t at =
      (3 * seq + static_cast<unsigned char>(robot[0])) % kDimension;
  trace.code[at] = 1.0f;
  trace.code[(at + 1) % kDimension] = 0.1f;
  float norm = 0;
  for (float x : trace.code) norm += x * x;
  for (float& x : trace.code) x /= std::sqrt(norm);
  return trace;
}

// The one nearest code, compared as a unit vector (as the engine asks).
SearchParams Nearest() {
  SearchParams params;
  params.k = 1;
  params.unit_query = true;
  return params;
}

std::vector<const MemoryTrace*> Pointers(const std::vector<MemoryTrace>& all) {
  std::vector<const MemoryTrace*> pointers;
  for (const MemoryTrace& trace : all) pointers.push_back(&trace);
  return pointers;
}

// What a snapshot holds of a FleetIndex: its handles and its index, read
// back as ReadSnapshot does.
struct Image {
  std::string handles;
  std::string index;
  uint64_t next_handle = 0;
  TraceHandles saved;
  std::unique_ptr<PlaceIndex> loaded;
};

Image Snapshot(const FleetIndex& index) {
  Image image;
  core::ByteWriter handles([&](std::span<const char> data) {
    image.handles.append(data.data(), data.size());
  });
  index.SaveHandles(handles);
  core::ByteWriter codes([&](std::span<const char> data) {
    image.index.append(data.data(), data.size());
  });
  EXPECT_TRUE(index.SaveIndex(codes).ok());
  core::ByteReader in(image.handles);
  EXPECT_TRUE(in.Get(&image.next_handle));
  EXPECT_TRUE(image.saved.Load(in, image.next_handle).ok());
  image.loaded = index::NewExactIndex(kDimension);
  core::ByteReader index_in(image.index);
  EXPECT_TRUE(image.loaded->Load(index_in).ok());
  return image;
}

TEST(FleetIndexTest, CodesAreFoundByTheirTracesKeys) {
  FleetIndex index;
  EXPECT_EQ(index.Add({}).code(), absl::StatusCode::kOk);  // nothing to add
  const std::vector<MemoryTrace> one = {Trace("a", 1)};
  EXPECT_EQ(index.Add(Pointers(one)).code(), absl::StatusCode::kInternal);

  index.Start(index::NewExactIndex(kDimension));
  const std::vector<MemoryTrace> traces = {Trace("a", 1), Trace("a", 2),
                                           Trace("b", 1)};
  ASSERT_TRUE(index.Add(Pointers(traces)).ok());
  EXPECT_EQ(index.size(), 3u);
  std::vector<float> code;
  ASSERT_TRUE(index.CopyCode(TraceKey{"a", 2}, &code));
  EXPECT_EQ(code, traces[1].code);
  EXPECT_FALSE(index.CopyCode(TraceKey{"c", 1}, &code));

  // A search's neighbours name their traces.
  const absl::StatusOr<std::vector<Neighbor>> found =
      index.get()->Search(traces[2].code, Nearest());
  ASSERT_TRUE(found.ok() && found->size() == 1u) << found.status();
  EXPECT_EQ(index.KeyOf((*found)[0].id), (TraceKey{"b", 1}));

  const TraceKey a1{"a", 1}, b1{"b", 1}, none{"z", 9};
  const std::vector<const TraceKey*> keys = {&a1, &none, &b1};
  EXPECT_EQ(index.HoldsCodes(keys), (std::vector<bool>{true, false, true}));
  std::vector<float> first, second;
  const std::vector<const TraceKey*> two = {&a1, &b1};
  const std::vector<std::vector<float>*> into = {&first, &second};
  ASSERT_TRUE(index.CopyCodes(two, into));
  EXPECT_EQ(first, traces[0].code);
  EXPECT_EQ(second, traces[2].code);

  ASSERT_TRUE(index.Remove({a1, none}).ok());
  EXPECT_EQ(index.size(), 2u);
  EXPECT_FALSE(index.CopyCode(a1, &code));
}

TEST(FleetIndexTest, TheSnapshotIsCurrentUntilTheNextChange) {
  FleetIndex index;
  index.Start(index::NewExactIndex(kDimension));
  EXPECT_FALSE(index.SnapshotCurrent());  // none written
  const std::vector<MemoryTrace> traces = {Trace("a", 1), Trace("a", 2)};
  ASSERT_TRUE(index.Add(Pointers(traces)).ok());
  index.SnapshotWritten(index.changes(), 0);
  EXPECT_TRUE(index.SnapshotCurrent());
  ASSERT_TRUE(index.Remove({TraceKey{"a", 1}}).ok());
  EXPECT_FALSE(index.SnapshotCurrent());
  // Removing what it does not hold changes nothing.
  index.SnapshotWritten(index.changes(), 0);
  ASSERT_TRUE(index.Remove({TraceKey{"a", 1}}).ok());
  EXPECT_TRUE(index.SnapshotCurrent());
  index.Reset();
  EXPECT_EQ(index.get(), nullptr);
  EXPECT_EQ(index.changes(), 0u);
  EXPECT_FALSE(index.SnapshotCurrent());
}

// Codes the tiered index's background thread links after a snapshot that
// held them unlinked make it stale: a load of it would link them again.
TEST(FleetIndexTest, CodesLinkedAfterASnapshotMakeItStale) {
  index::TieredIndexOptions options;
  options.hnsw_from = 10;
  FleetIndex index;
  index.Start(index::NewTieredIndex(kDimension, options));
  index.DeferIndexing(absl::InfiniteFuture());  // nothing linked meanwhile
  std::vector<MemoryTrace> traces;
  for (uint64_t seq = 1; seq <= 40; ++seq) traces.push_back(Trace("a", seq));
  ASSERT_TRUE(index.Add(Pointers(traces)).ok());
  const size_t unindexed = index.get()->unindexed();
  ASSERT_GT(unindexed, 0u);
  index.SnapshotWritten(index.changes(), unindexed);
  EXPECT_TRUE(index.SnapshotCurrent());
  ASSERT_TRUE(index.get()->IndexWaiting().ok());
  ASSERT_EQ(index.get()->unindexed(), 0u);
  EXPECT_FALSE(index.SnapshotCurrent());
  index.SnapshotWritten(index.changes(), 0);
  EXPECT_TRUE(index.SnapshotCurrent());
}

// A snapshot taken before the store moved on: what the store holds now is
// what the reconciled index holds, under handles that do not collide.
TEST(FleetIndexTest, ASnapshotIsReconciledWithTheStore) {
  FleetIndex before;
  before.Start(index::NewExactIndex(kDimension));
  const std::vector<MemoryTrace> then = {Trace("a", 1), Trace("a", 2),
                                         Trace("b", 1)};
  ASSERT_TRUE(before.Add(Pointers(then)).ok());
  Image image = Snapshot(before);

  // Since then: (a, 1) forgotten, (b, 2) and (c, 5) stored.
  const std::vector<MemoryTrace> now = {Trace("a", 2), Trace("b", 1),
                                        Trace("b", 2), Trace("c", 5)};
  FleetIndex after;
  absl::StatusOr<FleetIndex::Reconciled> reconciled =
      after.Reconcile(std::move(image.loaded), std::move(image.saved),
                      image.next_handle, Pointers(now));
  ASSERT_TRUE(reconciled.ok()) << reconciled.status();
  EXPECT_EQ(reconciled->kept, 2u);
  EXPECT_EQ(reconciled->added, 2u);
  EXPECT_EQ(reconciled->removed, 1u);
  EXPECT_EQ(after.size(), 4u);
  EXPECT_EQ(after.get()->size(), 4u);
  std::vector<float> code;
  EXPECT_FALSE(after.CopyCode(TraceKey{"a", 1}, &code));
  for (const MemoryTrace& trace : now) {
    ASSERT_TRUE(after.CopyCode(trace.key(), &code)) << trace.robot_id;
    EXPECT_EQ(code, trace.code);
    const absl::StatusOr<std::vector<Neighbor>> found =
        after.get()->Search(trace.code, Nearest());
    ASSERT_TRUE(found.ok() && found->size() == 1u) << found.status();
    EXPECT_EQ(after.KeyOf((*found)[0].id), trace.key());
  }
  EXPECT_EQ(after.changes(), 0u);
}

// A restart leaves the codes the snapshot holds in the store but for the
// sample CheckedOnLoad picks: the reconciled index answers with the
// snapshot's codes, and the sample still catches another history.
TEST(FleetIndexTest, TracesLoadedWithoutTheSnapshotsCodesAreReconciled) {
  FleetIndex before;
  before.Start(index::NewExactIndex(kDimension));
  std::vector<MemoryTrace> then;
  for (uint64_t seq = 1; seq <= 5000; ++seq) then.push_back(Trace("a", seq));
  ASSERT_TRUE(before.Add(Pointers(then)).ok());
  for (bool other_history : {false, true}) {
    Image image = Snapshot(before);
    std::vector<MemoryTrace> now = then;
    size_t kept_codes = 0;
    MemoryTrace* sampled = nullptr;
    for (MemoryTrace& trace : now) {
      const uint64_t handle = image.saved.Find(trace.key());
      ASSERT_NE(handle, 0u);
      if (FleetIndex::CheckedOnLoad(handle, image.saved.size())) {
        ++kept_codes;
        sampled = &trace;
      } else {
        trace.code.clear();
      }
    }
    EXPECT_GT(kept_codes, 800u);
    EXPECT_LT(kept_codes, 2600u);
    ASSERT_NE(sampled, nullptr);
    if (other_history) sampled->code = Trace("b", 1).code;
    FleetIndex after;
    absl::StatusOr<FleetIndex::Reconciled> reconciled =
        after.Reconcile(std::move(image.loaded), std::move(image.saved),
                        image.next_handle, Pointers(now));
    if (other_history) {
      EXPECT_EQ(reconciled.status().code(), absl::StatusCode::kDataLoss);
      EXPECT_EQ(after.get(), nullptr);
      continue;
    }
    ASSERT_TRUE(reconciled.ok()) << reconciled.status();
    EXPECT_EQ(reconciled->kept, then.size());
    std::vector<float> code;
    for (size_t i = 0; i < then.size(); i += 97) {
      ASSERT_TRUE(after.CopyCode(then[i].key(), &code));
      EXPECT_EQ(code, then[i].code);
    }
  }
}

TEST(FleetIndexTest, ASnapshotOfAnotherHistoryIsRefusedAndLeavesNoIndex) {
  FleetIndex before;
  before.Start(index::NewExactIndex(kDimension));
  const std::vector<MemoryTrace> then = {Trace("a", 1)};
  ASSERT_TRUE(before.Add(Pointers(then)).ok());
  Image image = Snapshot(before);

  std::vector<MemoryTrace> now = {Trace("a", 1)};
  now[0].code = Trace("a", 2).code;  // the same key, another code
  FleetIndex after;
  after.Start(index::NewExactIndex(kDimension));
  absl::StatusOr<FleetIndex::Reconciled> reconciled =
      after.Reconcile(std::move(image.loaded), std::move(image.saved),
                      image.next_handle, Pointers(now));
  EXPECT_EQ(reconciled.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(reconciled.status().message().find("\"a\", 1"), std::string::npos)
      << reconciled.status();
  EXPECT_EQ(after.get(), nullptr);
  EXPECT_EQ(after.size(), 0u);
}

// Traces without codes are taken as the snapshot's (the load found them
// in its handles): more of them than it holds cannot be, and is refused.
TEST(FleetIndexTest, MoreTracesWithoutCodesThanTheSnapshotHoldsAreRefused) {
  FleetIndex before;
  before.Start(index::NewExactIndex(kDimension));
  const std::vector<MemoryTrace> then = {Trace("a", 1), Trace("a", 2)};
  ASSERT_TRUE(before.Add(Pointers(then)).ok());
  Image image = Snapshot(before);

  std::vector<MemoryTrace> now = {Trace("a", 1), Trace("a", 2), Trace("a", 3)};
  for (MemoryTrace& trace : now) trace.code.clear();
  FleetIndex after;
  absl::StatusOr<FleetIndex::Reconciled> reconciled =
      after.Reconcile(std::move(image.loaded), std::move(image.saved),
                      image.next_handle, Pointers(now));
  EXPECT_EQ(reconciled.status().code(), absl::StatusCode::kDataLoss)
      << reconciled.status();
  EXPECT_EQ(after.get(), nullptr);
}

}  // namespace
}  // namespace fleetmem::engine
