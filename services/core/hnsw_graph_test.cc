#include "services/core/hnsw_graph.h"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <memory>
#include <random>
#include <span>
#include <string>
#include <system_error>
#include <thread>
#include <vector>

#include "gtest/gtest.h"

namespace fleetmem::core {
namespace {

// `count` vectors of `dimension` standard normal coordinates.
std::vector<std::vector<float>> Gaussian(size_t count, size_t dimension,
                                         uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<float> gauss(0.0f, 1.0f);
  std::vector<std::vector<float>> out(count, std::vector<float>(dimension));
  for (auto& v : out) {
    for (float& x : v) x = gauss(rng);
  }
  return out;
}

std::string Saved(const HnswGraph& graph) {
  std::string bytes;
  ByteWriter out([&](std::span<const char> chunk) {
    bytes.append(chunk.data(), chunk.size());
  });
  graph.Save(out);
  return bytes;
}

// A slot's vector as given, by copy (an int8 graph whose floats are kept
// outside memory has no pointer to give).
std::vector<float> Code(const HnswGraph& graph, uint32_t slot) {
  std::vector<float> code(graph.dimension());
  graph.CopyVector(slot, code.data());
  return code;
}

// What CopiedRows is told to fail.
struct RowFaults {
  bool refuse_growth = false;
  int writes_left = -1;  // < 0: every write succeeds
};

// Float rows on the heap that are read only by copy, as a file's are (Find
// gives no pointer), and fail as `faults` says, as a full disk would.
class CopiedRows final : public FloatRows {
 public:
  CopiedRows(size_t width, std::shared_ptr<RowFaults> faults)
      : FloatRows(width), faults_(std::move(faults)) {}
  void Reserve(size_t rows) override {
    if (rows * width() <= values_.size()) return;
    if (faults_->refuse_growth) {
      throw std::system_error(ENOSPC, std::generic_category(), "test rows");
    }
    values_.resize(rows * width());
  }
  void Write(size_t first, size_t count, const float* values) override {
    if (faults_->writes_left == 0) {
      throw std::system_error(EIO, std::generic_category(), "test rows");
    }
    if (faults_->writes_left > 0) --faults_->writes_left;
    std::copy(values, values + count * width(),
              values_.begin() + first * width());
  }
  void Read(size_t first, size_t count, float* values) const override {
    std::copy(values_.begin() + first * width(),
              values_.begin() + (first + count) * width(), values);
  }
  size_t MemoryBytes() const override { return 0; }

 private:
  std::shared_ptr<RowFaults> faults_;
  std::vector<float> values_;
};

FloatRowsMaker CopiedRowsWith(std::shared_ptr<RowFaults> faults) {
  return [faults](size_t width) {
    return std::make_unique<CopiedRows>(width, faults);
  };
}

// Stages vectors[first, first + count) (scales 1 + index / 1000 when the
// graph is scaled) and links them on `threads` threads, in order when 1.
HnswGraph::Staged StageAndLink(HnswGraph& graph,
                               const std::vector<std::vector<float>>& vectors,
                               size_t first, size_t count, bool scaled,
                               int threads) {
  std::vector<const float*> data;
  std::vector<float> scales;
  for (size_t i = first; i < first + count; ++i) {
    data.push_back(vectors[i].data());
    scales.push_back(scaled ? 1.0f + static_cast<float>(i) / 1000.0f : 1.0f);
  }
  HnswGraph::Staged staged = graph.Stage(data, scales);
  std::atomic<size_t> next{staged.linked};
  auto link = [&] {
    for (size_t i; (i = next.fetch_add(1)) < staged.slots.size();) {
      graph.Link(staged, i);
    }
  };
  std::vector<std::thread> helpers;
  for (int t = 1; t < threads; ++t) helpers.emplace_back(link);
  link();
  for (std::thread& helper : helpers) helper.join();
  return staged;
}

// The graph's three node layouts, int8 with its floats in memory or read
// by copy.
enum class Nodes { kPlain, kScaled, kInt8, kInt8CopiedFloats };

class HnswGraphStageTest : public ::testing::TestWithParam<Nodes> {
 protected:
  HnswGraphOptions Options() const {
    HnswGraphOptions options;
    options.m = 8;
    options.ef_construction = 32;
    options.scaled = GetParam() != Nodes::kPlain;
    options.int8 =
        GetParam() == Nodes::kInt8 || GetParam() == Nodes::kInt8CopiedFloats;
    if (GetParam() == Nodes::kInt8CopiedFloats) {
      options.float_rows = CopiedRowsWith(std::make_shared<RowFaults>());
    }
    return options;
  }
  bool Scaled() const { return GetParam() != Nodes::kPlain; }
};

TEST_P(HnswGraphStageTest, LinkedInOrderItIsTheGraphOfTheAdds) {
  constexpr size_t kDimension = 12;
  const auto vectors = Gaussian(500, kDimension, 7);
  const bool scaled = Scaled();
  HnswGraph added(kDimension, Options());
  HnswGraph staged(kDimension, Options());
  std::vector<uint32_t> added_slots;
  auto add = [&](size_t first, size_t count) {
    for (size_t i = first; i < first + count; ++i) {
      added_slots.push_back(
          added.Add(vectors[i].data(),
                    scaled ? 1.0f + static_cast<float>(i) / 1000.0f : 1.0f));
    }
  };
  add(0, 300);
  HnswGraph::Staged first = StageAndLink(staged, vectors, 0, 300, scaled, 1);
  EXPECT_EQ(first.linked, 1u);  // an empty graph's entry point
  EXPECT_TRUE(first.complete);
  // Removed slots are refilled first, as Add refills them.
  for (uint32_t slot = 10; slot < 200; slot += 10) {
    added.Remove(slot);
    staged.Remove(slot);
  }
  add(300, 200);
  HnswGraph::Staged second = StageAndLink(staged, vectors, 300, 200, scaled, 1);
  EXPECT_EQ(second.linked, 19u);
  std::vector<uint32_t> staged_slots = first.slots;
  staged_slots.insert(staged_slots.end(), second.slots.begin(),
                      second.slots.end());
  EXPECT_EQ(staged_slots, added_slots);
  EXPECT_EQ(staged.size(), added.size());
  EXPECT_TRUE(Saved(staged) == Saved(added));
}

TEST_P(HnswGraphStageTest, ConcurrentlyLinkedNodesAreFoundAndSaveWhole) {
  constexpr size_t kDimension = 16;
  constexpr size_t kCount = 3000;
  const auto vectors = Gaussian(kCount, kDimension, 11);
  const bool scaled = Scaled();
  HnswGraph graph(kDimension, Options());
  size_t removed = 0;
  for (size_t first = 0; first < kCount; first += 250) {
    if (first == 1000) {  // refills mixed with new nodes
      for (uint32_t slot = 0; slot < 100; slot += 5, ++removed) {
        graph.Remove(slot);
      }
    }
    StageAndLink(graph, vectors, first, 250, scaled, 4);
  }
  ASSERT_EQ(graph.size(), kCount - removed);
  ASSERT_EQ(graph.slot_count(), kCount - removed);
  size_t found = 0;
  for (uint32_t slot = 0; slot < graph.slot_count(); ++slot) {
    const auto nearest =
        graph.Search(Code(graph, slot).data(), 1, graph.Scale(slot));
    found += !nearest.empty() && nearest[0].second == slot;
  }
  EXPECT_GE(found, graph.size() * 995 / 1000);
  // Load checks every link and slot: the concurrent links left none bad.
  const std::string bytes = Saved(graph);
  ByteReader in(std::span<const char>(bytes.data(), bytes.size()));
  absl::StatusOr<std::unique_ptr<HnswGraph>> loaded =
      HnswGraph::Load(kDimension, Options(), in);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  for (uint32_t slot = 0; slot < graph.slot_count(); slot += 97) {
    const std::vector<float> code = Code(graph, slot);
    EXPECT_EQ((*loaded)->Search(code.data(), 5, graph.Scale(slot)),
              graph.Search(code.data(), 5, graph.Scale(slot)));
  }
}

// On a graph that does not change, SearchBesideLinks walks as hnswlib's
// search does: the same answers, with removed nodes and without.
TEST_P(HnswGraphStageTest, SearchBesideLinksAnswersAsSearch) {
  constexpr size_t kDimension = 16;
  const auto vectors = Gaussian(2000, kDimension, 13);
  const auto queries = Gaussian(50, kDimension, 17);
  HnswGraph graph(kDimension, Options());
  StageAndLink(graph, vectors, 0, 2000, Scaled(), 1);
  for (int round = 0; round < 2; ++round) {
    for (const auto& query : queries) {
      for (size_t k : {1, 10, 40}) {
        const float scale = Scaled() ? 1.5f : 1.0f;
        EXPECT_EQ(graph.SearchBesideLinks(query.data(), k, scale),
                  graph.Search(query.data(), k, scale));
      }
    }
    for (uint32_t slot = 0; slot < 2000; slot += 3) {
      if (round == 0) graph.Remove(slot);
    }
  }
  EXPECT_TRUE(HnswGraph(kDimension, Options())
                  .SearchBesideLinks(queries[0].data(), 5)
                  .empty());
}

// Searches beside concurrent Link calls (ThreadSanitizer: make test-tsan)
// find only stored slots, nearest first, and every node once it is linked.
// (Stage changes the graph's storage: nothing may run beside it.)
TEST_P(HnswGraphStageTest, SearchBesideLinksRunsWhileNodesAreLinked) {
  constexpr size_t kDimension = 16;
  constexpr size_t kCount = 2000;
  const auto vectors = Gaussian(kCount, kDimension, 19);
  const bool scaled = Scaled();
  HnswGraph graph(kDimension, Options());
  StageAndLink(graph, vectors, 0, 500, scaled, 1);
  size_t searches = 0;
  for (size_t first = 500; first < kCount; first += 250) {
    std::vector<const float*> data;
    std::vector<float> scales;
    for (size_t i = first; i < first + 250; ++i) {
      data.push_back(vectors[i].data());
      scales.push_back(scaled ? 1.0f + static_cast<float>(i) / 1000.0f : 1.0f);
    }
    const HnswGraph::Staged staged = graph.Stage(data, scales);
    std::atomic<bool> linked{false};
    std::thread searcher([&, seed = first] {
      std::mt19937 rng(seed);
      do {
        const auto& query = vectors[rng() % kCount];
        const auto found = graph.SearchBesideLinks(query.data(), 5);
        for (size_t i = 0; i < found.size(); ++i) {
          EXPECT_LT(found[i].second, graph.slot_count());
          if (i > 0) EXPECT_LE(found[i - 1].first, found[i].first);
        }
        ++searches;
      } while (!linked.load());
    });
    std::atomic<size_t> next{staged.linked};
    auto link = [&] {
      for (size_t i; (i = next.fetch_add(1)) < staged.slots.size();) {
        graph.Link(staged, i);
      }
    };
    std::thread helper(link);
    link();
    helper.join();
    linked.store(true);
    searcher.join();
  }
  EXPECT_GT(searches, 0u);
  size_t found = 0;
  for (uint32_t slot = 0; slot < graph.slot_count(); ++slot) {
    const auto nearest =
        graph.SearchBesideLinks(Code(graph, slot).data(), 1, graph.Scale(slot));
    found += !nearest.empty() && nearest[0].second == slot;
  }
  EXPECT_GE(found, kCount * 995 / 1000);
}

// A scan visits every live slot the filter wants once, in slot order, at
// its precise distance, across chunks of rows (more than 4,096 slots).
TEST_P(HnswGraphStageTest, ScanPreciseVisitsEachWantedLiveSlotOnce) {
  constexpr size_t kDimension = 8;
  const auto vectors = Gaussian(5000, kDimension, 43);
  HnswGraph graph(kDimension, Options());
  StageAndLink(graph, vectors, 0, vectors.size(), Scaled(), 1);
  for (uint32_t slot = 4000; slot < 4200; ++slot) graph.Remove(slot);
  const auto query = Gaussian(1, kDimension, 47)[0];
  const float scale = Scaled() ? 1.5f : 1.0f;
  std::vector<uint32_t> visited;
  graph.ScanPrecise(
      query.data(), scale, [](uint32_t slot) { return slot % 3 != 0; },
      [&](uint32_t slot, double squared) {
        visited.push_back(slot);
        EXPECT_EQ(squared,
                  graph.PreciseSquaredDistance(query.data(), slot, scale));
      });
  std::vector<uint32_t> expected;
  for (uint32_t slot = 0; slot < 5000; ++slot) {
    if (slot % 3 != 0 && (slot < 4000 || slot >= 4200)) {
      expected.push_back(slot);
    }
  }
  EXPECT_EQ(visited, expected);
}

// The batch reads (a search's candidates, a sample's codes) answer as one
// read per slot: the same distances and the same floats, bit for bit, for
// slots in any order and repeated; a slot never added is refused.
TEST_P(HnswGraphStageTest, BatchesAnswerAsOneSlotAtATime) {
  constexpr size_t kDimension = 10;
  const auto vectors = Gaussian(300, kDimension, 53);
  HnswGraph graph(kDimension, Options());
  StageAndLink(graph, vectors, 0, vectors.size(), Scaled(), 1);
  graph.Remove(17);
  const std::vector<uint32_t> slots = {299, 0, 42, 42, 150, 1, 298, 0};
  const auto query = Gaussian(1, kDimension, 59)[0];
  const float scale = Scaled() ? 0.75f : 1.0f;
  const std::vector<double> squared =
      graph.PreciseSquaredDistances(query.data(), slots, scale);
  ASSERT_EQ(squared.size(), slots.size());
  std::vector<std::vector<float>> copies(slots.size());
  std::vector<float*> out;
  for (auto& copy : copies) {
    copy.assign(kDimension, -1.0f);
    out.push_back(copy.data());
  }
  graph.CopyVectors(slots, out);
  for (size_t i = 0; i < slots.size(); ++i) {
    EXPECT_EQ(squared[i],
              graph.PreciseSquaredDistance(query.data(), slots[i], scale))
        << "slot " << slots[i];
    EXPECT_EQ(copies[i], vectors[slots[i]]) << "slot " << slots[i];
  }
  EXPECT_TRUE(graph.PreciseSquaredDistances(query.data(), {}, scale).empty());
  const std::vector<uint32_t> unknown = {3, 1000};
  EXPECT_THROW(graph.PreciseSquaredDistances(query.data(), unknown, scale),
               std::out_of_range);
}

INSTANTIATE_TEST_SUITE_P(EveryLayout, HnswGraphStageTest,
                         ::testing::Values(Nodes::kPlain, Nodes::kScaled,
                                           Nodes::kInt8,
                                           Nodes::kInt8CopiedFloats));

HnswGraphOptions Int8Options() {
  return {.m = 8, .ef_construction = 32, .scaled = true, .int8 = true};
}

// An int8 graph keeps the floats as given (bit for bit, with their scales)
// and walks on distances within a quantum of the precise ones; its
// answers, rescored, are the exact nearest as often as a float graph's.
TEST(HnswGraphInt8Test, KeepsTheFloatsAndWalksOnCloseDistances) {
  constexpr size_t kDimension = 40;  // not a multiple of 16: padded nodes
  const auto vectors = Gaussian(3000, kDimension, 23);
  HnswGraph graph(kDimension, Int8Options());
  HnswGraph floats(kDimension, {.m = 8, .ef_construction = 32, .scaled = true});
  for (size_t i = 0; i < vectors.size(); ++i) {
    const float scale = 1.0f + static_cast<float>(i % 7) / 10.0f;
    ASSERT_EQ(graph.Add(vectors[i].data(), scale), i);
    floats.Add(vectors[i].data(), scale);
  }
  for (uint32_t slot = 0; slot < 3000; slot += 37) {
    EXPECT_TRUE(std::equal(vectors[slot].begin(), vectors[slot].end(),
                           graph.Vector(slot)));
    EXPECT_EQ(graph.Scale(slot), 1.0f + static_cast<float>(slot % 7) / 10.0f);
  }
  const auto queries = Gaussian(100, kDimension, 29);
  size_t int8_hits = 0, float_hits = 0;
  for (const auto& query : queries) {
    const auto found = graph.Search(query.data(), 20);
    ASSERT_EQ(found.size(), 20u);
    for (const auto& [quantized, slot] : found) {
      const double precise = graph.PreciseSquaredDistance(query.data(), slot);
      // |q - p|² differs from |q - p'|² by at most about 2 |q - p| |p - p'|
      // + |p - p'|², p' within half a quantum (max |p| / 254) a coordinate.
      EXPECT_NEAR(quantized, precise, 0.05 * precise + 1.0) << slot;
    }
    // The exact nearest, by a scan of the floats.
    uint32_t nearest = 0;
    for (uint32_t slot = 1; slot < 3000; ++slot) {
      if (graph.PreciseSquaredDistance(query.data(), slot) <
          graph.PreciseSquaredDistance(query.data(), nearest)) {
        nearest = slot;
      }
    }
    uint32_t best = found[0].second;
    for (const auto& [quantized, slot] : found) {
      if (graph.PreciseSquaredDistance(query.data(), slot) <
          graph.PreciseSquaredDistance(query.data(), best)) {
        best = slot;
      }
    }
    int8_hits += best == nearest;
    float_hits += floats.Search(query.data(), 1)[0].second == nearest;
  }
  EXPECT_GE(int8_hits, 95u);
  EXPECT_GE(int8_hits + 2, float_hits);
  EXPECT_GT(graph.MemoryBytes(), 3000 * (kDimension + 1) * sizeof(float));
}

// A float graph's snapshot does not load as an int8 one (nor the other
// way round): the error names both; a truncated int8 snapshot is refused.
TEST(HnswGraphInt8Test, LoadRefusesAnotherLayoutAndMissingFloats) {
  constexpr size_t kDimension = 16;
  const auto vectors = Gaussian(200, kDimension, 31);
  HnswGraphOptions float_options = Int8Options();
  float_options.int8 = false;
  HnswGraph int8(kDimension, Int8Options()), floats(kDimension, float_options);
  for (const auto& v : vectors) {
    int8.Add(v.data(), 2.0f);
    floats.Add(v.data(), 2.0f);
  }
  const std::string int8_bytes = Saved(int8), float_bytes = Saved(floats);
  auto load = [&](const std::string& bytes, HnswGraphOptions options) {
    ByteReader in(std::span<const char>(bytes.data(), bytes.size()));
    return HnswGraph::Load(kDimension, options, in);
  };
  absl::StatusOr<std::unique_ptr<HnswGraph>> crossed =
      load(float_bytes, Int8Options());
  ASSERT_EQ(crossed.status().code(), absl::StatusCode::kDataLoss);
  EXPECT_NE(crossed.status().message().find("int8 0"), std::string::npos)
      << crossed.status();
  EXPECT_EQ(load(int8_bytes, float_options).status().code(),
            absl::StatusCode::kDataLoss);
  EXPECT_EQ(load(int8_bytes.substr(0, int8_bytes.size() - 4), Int8Options())
                .status()
                .code(),
            absl::StatusCode::kDataLoss);
  absl::StatusOr<std::unique_ptr<HnswGraph>> loaded =
      load(int8_bytes, Int8Options());
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_TRUE(Saved(**loaded) == int8_bytes);
  EXPECT_TRUE(
      std::equal(vectors[7].begin(), vectors[7].end(), (*loaded)->Vector(7)));
}

// An int8 graph writes its floats as self-checked bytes, each row's
// RowCheck after them: a load that copies the rows checks each (a flipped
// bit in a row or in its check is DATA_LOSS naming the slot). The layout
// before the checks (GRF4: the same bytes without them) still loads.
TEST(HnswGraphInt8Test, EachRowOfFloatsIsCheckedWhenItIsCopied) {
  constexpr size_t kDimension = 16;
  constexpr size_t kCount = 200;
  const auto vectors = Gaussian(kCount, kDimension, 37);
  HnswGraph graph(kDimension, Int8Options());
  for (const auto& v : vectors) graph.Add(v.data(), 2.0f);
  std::string bytes;
  size_t floats_at = 0, floats_size = 0;
  ByteWriter out(
      [&](std::span<const char> chunk) {
        bytes.append(chunk.data(), chunk.size());
      },
      nullptr,
      [&](std::span<const char> chunk) {
        if (floats_size == 0) floats_at = bytes.size();
        floats_size += chunk.size();
        bytes.append(chunk.data(), chunk.size());
      });
  graph.Save(out);
  const size_t row_bytes = (kDimension + 1) * sizeof(float);
  ASSERT_EQ(floats_size, kCount * row_bytes);
  ASSERT_EQ(bytes.size(), floats_at + floats_size + kCount * sizeof(uint32_t));
  auto load = [&](const std::string& saved) {
    ByteReader in(std::span<const char>(saved.data(), saved.size()));
    return HnswGraph::Load(kDimension, Int8Options(), in);
  };
  ASSERT_TRUE(load(bytes).ok());
  // From a file, into rows that keep none (on the heap): copied and
  // checked all the same.
  const FileBytes file{.descriptor = std::make_shared<const int>(-1)};
  ByteReader from_file(std::span<const char>(bytes.data(), bytes.size()),
                       &file);
  absl::StatusOr<std::unique_ptr<HnswGraph>> copied =
      HnswGraph::Load(kDimension, Int8Options(), from_file);
  ASSERT_TRUE(copied.ok()) << copied.status();
  EXPECT_EQ(Saved(**copied), Saved(graph));
  for (const size_t at : {floats_at + 50 * row_bytes + 5,
                          floats_at + floats_size + 50 * sizeof(uint32_t)}) {
    std::string damaged = bytes;
    damaged[at] ^= 0x20;
    const absl::StatusOr<std::unique_ptr<HnswGraph>> loaded = load(damaged);
    EXPECT_EQ(loaded.status().code(), absl::StatusCode::kDataLoss);
    EXPECT_NE(loaded.status().message().find("slot 50 fail their checksum"),
              std::string::npos)
        << loaded.status();
  }
  std::string earlier = bytes.substr(0, floats_at + floats_size);
  const uint32_t grf4 = 0x47524634;
  std::memcpy(earlier.data(), &grf4, sizeof(grf4));
  const absl::StatusOr<std::unique_ptr<HnswGraph>> loaded = load(earlier);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(Saved(**loaded), Saved(graph));
  EXPECT_TRUE(
      std::equal(vectors[7].begin(), vectors[7].end(), (*loaded)->Vector(7)));
}

// Floats that cannot be kept (a full disk, a failed write) leave the graph
// as it was: Add throws before it changes anything, Stage stages nothing
// more and says so; once they can be kept again, the graph goes on.
TEST(HnswGraphInt8Test, FloatsThatCannotBeKeptLeaveTheGraphAsItWas) {
  constexpr size_t kDimension = 16;
  const auto vectors = Gaussian(120, kDimension, 37);
  auto faults = std::make_shared<RowFaults>();
  HnswGraphOptions options = Int8Options();
  options.float_rows = CopiedRowsWith(faults);
  HnswGraph graph(kDimension, options);
  for (size_t i = 0; i < 50; ++i) graph.Add(vectors[i].data(), 1.5f);
  EXPECT_EQ(graph.Vector(3), nullptr);  // read by copy only
  EXPECT_EQ(Code(graph, 3), vectors[3]);
  std::string before = Saved(graph);
  auto stage = [&](size_t first, size_t count) {
    std::vector<const float*> data;
    for (size_t i = first; i < first + count; ++i) {
      data.push_back(vectors[i].data());
    }
    return graph.Stage(data, std::vector<float>(count, 1.5f));
  };

  faults->refuse_growth = true;  // no room for the next rows
  EXPECT_THROW(graph.Add(vectors[50].data(), 1.5f), std::system_error);
  EXPECT_THROW(stage(50, 10), std::system_error);
  EXPECT_EQ(graph.size(), 50u);
  EXPECT_TRUE(Saved(graph) == before);

  faults->refuse_growth = false;
  faults->writes_left = 0;  // the 10 new rows' write fails
  HnswGraph::Staged staged = stage(50, 10);
  EXPECT_FALSE(staged.complete);
  EXPECT_TRUE(staged.slots.empty());
  EXPECT_EQ(graph.size(), 50u);
  EXPECT_TRUE(Saved(graph) == before);

  graph.Remove(7);  // a refill's row fails: nothing staged either
  before = Saved(graph);
  faults->writes_left = 0;
  staged = stage(50, 10);
  EXPECT_FALSE(staged.complete);
  EXPECT_TRUE(staged.slots.empty());
  EXPECT_TRUE(Saved(graph) == before);

  faults->writes_left = -1;
  staged = stage(50, 70);
  ASSERT_TRUE(staged.complete);
  for (size_t i = staged.linked; i < staged.slots.size(); ++i) {
    graph.Link(staged, i);
  }
  EXPECT_EQ(graph.size(), 119u);
  for (size_t i = 0; i < staged.slots.size(); ++i) {
    EXPECT_EQ(Code(graph, staged.slots[i]), vectors[50 + i]);
    EXPECT_EQ(graph.Search(vectors[50 + i].data(), 1, 1.5f)[0].second,
              staged.slots[i]);
  }
}

}  // namespace
}  // namespace fleetmem::core
