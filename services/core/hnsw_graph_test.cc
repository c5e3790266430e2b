#include "services/core/hnsw_graph.h"

#include <atomic>
#include <random>
#include <span>
#include <string>
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

class HnswGraphStageTest : public ::testing::TestWithParam<bool> {
 protected:
  HnswGraphOptions Options() const {
    HnswGraphOptions options;
    options.m = 8;
    options.ef_construction = 32;
    options.scaled = GetParam();
    return options;
  }
};

TEST_P(HnswGraphStageTest, LinkedInOrderItIsTheGraphOfTheAdds) {
  constexpr size_t kDimension = 12;
  const auto vectors = Gaussian(500, kDimension, 7);
  const bool scaled = GetParam();
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
  const bool scaled = GetParam();
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
    const auto nearest = graph.Search(graph.Vector(slot), 1, graph.Scale(slot));
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
    EXPECT_EQ((*loaded)->Search(graph.Vector(slot), 5, graph.Scale(slot)),
              graph.Search(graph.Vector(slot), 5, graph.Scale(slot)));
  }
}

// On a graph that does not change, SearchBesideLinks walks as hnswlib's
// search does: the same answers, with removed nodes and without.
TEST_P(HnswGraphStageTest, SearchBesideLinksAnswersAsSearch) {
  constexpr size_t kDimension = 16;
  const auto vectors = Gaussian(2000, kDimension, 13);
  const auto queries = Gaussian(50, kDimension, 17);
  HnswGraph graph(kDimension, Options());
  StageAndLink(graph, vectors, 0, 2000, GetParam(), 1);
  for (int round = 0; round < 2; ++round) {
    for (const auto& query : queries) {
      for (size_t k : {1, 10, 40}) {
        const float scale = GetParam() ? 1.5f : 1.0f;
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
  const bool scaled = GetParam();
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
        graph.SearchBesideLinks(graph.Vector(slot), 1, graph.Scale(slot));
    found += !nearest.empty() && nearest[0].second == slot;
  }
  EXPECT_GE(found, kCount * 995 / 1000);
}

INSTANTIATE_TEST_SUITE_P(PlainAndScaled, HnswGraphStageTest, ::testing::Bool());

}  // namespace
}  // namespace fleetmem::core
