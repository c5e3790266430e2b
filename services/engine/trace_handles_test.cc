#include "services/engine/trace_handles.h"

#include <map>
#include <random>
#include <string>
#include <tuple>

#include "gtest/gtest.h"

namespace fleetmem::engine {
namespace {

using core::TraceKey;

std::string Saved(const TraceHandles& handles) {
  std::string bytes;
  core::ByteWriter out([&bytes](std::span<const char> data) {
    bytes.append(data.data(), data.size());
  });
  handles.Save(out);
  return bytes;
}

// Every entry, as (handle -> key), through ForEach.
std::map<uint64_t, TraceKey> Entries(const TraceHandles& handles) {
  std::map<uint64_t, TraceKey> entries;
  handles.ForEach([&](uint64_t handle, std::string_view robot, uint64_t seq) {
    entries[handle] = TraceKey{std::string(robot), seq};
  });
  return entries;
}

// Both directions agree with a plain map through random assignments and
// erasures by key and by handle, robots of every id length included.
TEST(TraceHandlesTest, BothDirectionsMatchAReferenceThroughChurn) {
  TraceHandles handles;
  std::map<uint64_t, TraceKey> reference;  // handle -> key
  std::mt19937_64 rng(5);
  const std::vector<std::string> robots = {"r", "robot-2", std::string(40, 'x'),
                                           ""};
  std::uniform_int_distribution<int> robot(0, robots.size() - 1);
  std::uniform_int_distribution<uint64_t> seq(0, 50);
  std::uniform_int_distribution<int> op(0, 9);
  uint64_t next = 1;
  auto erase_key = [&](const TraceKey& key) {
    for (auto it = reference.begin(); it != reference.end(); ++it) {
      if (it->second == key) return reference.erase(it), true;
    }
    return false;
  };
  for (int step = 0; step < 5000; ++step) {
    const TraceKey key{robots[robot(rng)], seq(rng)};
    const int what = op(rng);
    if (what < 6) {
      erase_key(key);
      handles.Assign(key, next);
      reference[next++] = key;
    } else if (what < 8) {
      const uint64_t handle = handles.Erase(key);
      const bool had = erase_key(key);
      EXPECT_EQ(handle != 0, had) << step;
    } else if (!reference.empty()) {
      const uint64_t handle = reference.begin()->first;
      EXPECT_TRUE(handles.EraseHandle(handle));
      EXPECT_FALSE(handles.EraseHandle(handle));
      reference.erase(handle);
    }
    ASSERT_EQ(handles.size(), reference.size()) << step;
  }
  EXPECT_EQ(Entries(handles), reference);
  for (const auto& [handle, key] : reference) {
    EXPECT_EQ(handles.Find(key), handle);
    EXPECT_EQ(handles.Key(handle), key);
  }
  EXPECT_EQ(handles.Find(TraceKey{"unknown robot", 1}), 0u);
  EXPECT_FALSE(handles.Key(next).has_value());
}

// A handle given again to another key leaves the first key without one.
TEST(TraceHandlesTest, AssignReplacesBothDirections) {
  TraceHandles handles;
  handles.Assign(TraceKey{"a", 1}, 7);
  handles.Assign(TraceKey{"a", 1}, 8);  // the key moves to a new handle
  EXPECT_EQ(handles.Find(TraceKey{"a", 1}), 8u);
  EXPECT_FALSE(handles.Key(7).has_value());
  handles.Assign(TraceKey{"b", 2}, 8);  // the handle moves to a new key
  EXPECT_EQ(handles.Find(TraceKey{"a", 1}), 0u);
  EXPECT_EQ(handles.Key(8), (TraceKey{"b", 2}));
  EXPECT_EQ(handles.size(), 1u);
}

TEST(TraceHandlesTest, SavedTableLoadsEqualAndBadBytesAreRefused) {
  TraceHandles handles;
  for (uint64_t i = 1; i <= 300; ++i) {
    handles.Assign(TraceKey{"robot-" + std::to_string(i % 7), i * 3}, i);
  }
  handles.Erase(TraceKey{"robot-1", 3});
  const std::string bytes = Saved(handles);
  EXPECT_EQ(handles.SavedSize(), bytes.size());
  EXPECT_EQ(TraceHandles().SavedSize(), Saved(TraceHandles()).size());
  TraceHandles loaded;
  core::ByteReader in(bytes);
  ASSERT_TRUE(loaded.Load(in, 301).ok());
  EXPECT_EQ(in.remaining(), 0u);
  EXPECT_EQ(Entries(loaded), Entries(handles));
  EXPECT_EQ(loaded.Find(TraceKey{"robot-2", 6}), 2u);

  // Into a used table, a handle out of range, cut bytes: refused, and a
  // failed load leaves the table empty.
  core::ByteReader again(bytes);
  EXPECT_EQ(loaded.Load(again, 301).code(),
            absl::StatusCode::kFailedPrecondition);
  TraceHandles small;
  core::ByteReader range(bytes);
  EXPECT_EQ(small.Load(range, 300).code(), absl::StatusCode::kDataLoss);
  EXPECT_TRUE(small.empty());
  for (size_t cut :
       {size_t{0}, size_t{5}, bytes.size() / 2, bytes.size() - 1}) {
    TraceHandles part;
    core::ByteReader in_part(std::string_view(bytes).substr(0, cut));
    EXPECT_EQ(part.Load(in_part, 301).code(), absl::StatusCode::kDataLoss)
        << "cut at " << cut;
    EXPECT_TRUE(part.empty());
  }
  // Two entries under one handle.
  TraceHandles twice_table;
  std::string twice;
  core::ByteWriter writer([&twice](std::span<const char> data) {
    twice.append(data.data(), data.size());
  });
  writer.Put<uint64_t>(1);
  writer.PutString("r");
  writer.Put<uint64_t>(2);
  for (uint64_t seq : {1, 2}) {
    writer.Put<uint32_t>(0);
    writer.Put<uint64_t>(seq);
    writer.Put<uint64_t>(5);
  }
  core::ByteReader twice_in(twice);
  EXPECT_EQ(twice_table.Load(twice_in, 10).code(), absl::StatusCode::kDataLoss);
}

}  // namespace
}  // namespace fleetmem::engine
