#include "services/engine/memory_image.h"

#include <cstdint>
#include <cstring>
#include <fstream>
#include <iterator>
#include <map>
#include <span>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "fleetmem_paths.h"
#include "gtest/gtest.h"

namespace fleetmem::engine {
namespace {

core::MemoryTrace Trace(std::string robot, uint64_t seq, uint64_t cluster) {
  core::MemoryTrace trace;
  trace.robot_id = std::move(robot);
  trace.seq = seq;
  trace.domain = seq % 2 == 0 ? "summer" : "winter";
  trace.encoder_version = "hog-v1";
  trace.code = {1.0f, 2.0f, 3.0f};
  trace.place = {1.5 * seq, -2.25, 0.125, 3.0};
  trace.reward = 0.75f;
  trace.reward_external = 0.5f;
  trace.reward_internal = 0.25f;
  trace.timestamp_ns = 1'700'000'000'000'000'000 + seq;
  trace.replay_count = static_cast<uint32_t>(seq * 3);
  trace.cluster_id = cluster;
  if (seq == 2) trace.attachment = std::string("scan\0bytes", 10);
  return trace;
}

std::map<uint64_t, core::Cluster> Clusters() {
  std::map<uint64_t, core::Cluster> clusters;
  core::Cluster& first = clusters[4];
  first.id = 4;
  first.robot_id = "r1";
  first.centroid = {0.5f, -1.0f, 7.0f, 2.0f};
  first.traces = {Trace("r1", 1, 4), Trace("r1", 2, 4), Trace("r2", 9, 4)};
  core::Cluster& second = clusters[11];
  second.id = 11;
  second.robot_id = "r2";
  second.centroid = {1.0f};
  second.traces = {Trace("r2", 10, 11)};
  core::Cluster& empty = clusters[12];  // no traces: still a cluster
  empty.id = 12;
  empty.robot_id = "a-robot-with-a-longer-name-than-sso";
  return clusters;
}

std::string Saved(const std::map<uint64_t, core::Cluster>& clusters) {
  std::string bytes;
  core::ByteWriter out([&bytes](std::span<const char> data) {
    bytes.append(data.data(), data.size());
  });
  SaveMemoryImage(
      clusters,
      [&clusters](uint64_t id) {
        return std::span<const float>(clusters.at(id).centroid);
      },
      out);
  // The length it starts with is that of the rest.
  uint64_t size = 0;
  EXPECT_GE(bytes.size(), sizeof(size));
  std::memcpy(&size, bytes.data(), sizeof(size));
  EXPECT_EQ(size, bytes.size() - sizeof(size));
  return bytes.substr(sizeof(size));
}

// Every field but the code, as a string to compare.
std::string Describe(const core::Cluster& cluster) {
  std::string out = absl::StrCat(cluster.id, " ", cluster.robot_id, " [");
  for (float value : cluster.centroid) absl::StrAppend(&out, value, ",");
  absl::StrAppend(&out, "]");
  for (const core::MemoryTrace& trace : cluster.traces) {
    absl::StrAppend(
        &out, "\n  ", trace.robot_id, "/", trace.seq, " ", trace.domain, " ",
        trace.encoder_version, " (", trace.place.x, ",", trace.place.y, ",",
        trace.place.z, ",", trace.place.yaw, ") ", trace.reward, " ",
        trace.reward_external, " ", trace.reward_internal, " ",
        trace.timestamp_ns, " ", trace.replay_count, " ", trace.cluster_id, " ",
        absl::CHexEscape(trace.attachment), " code:", trace.code.size());
  }
  return out;
}

TEST(MemoryImageTest, RoundTripKeepsEveryFieldButTheCodes) {
  const std::map<uint64_t, core::Cluster> clusters = Clusters();
  const std::string bytes = Saved(clusters);
  core::ByteReader in(bytes);
  absl::StatusOr<std::vector<core::Cluster>> loaded = LoadMemoryImage(in);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_EQ(in.remaining(), 0u);
  ASSERT_EQ(loaded->size(), clusters.size());
  auto want = clusters.begin();
  for (const core::Cluster& cluster : *loaded) {
    core::Cluster expected = want->second;
    for (core::MemoryTrace& trace : expected.traces) trace.code.clear();
    EXPECT_EQ(Describe(cluster), Describe(expected));
    ++want;
  }
  // No clusters: an image of none.
  const std::string none = Saved({});
  core::ByteReader empty(none);
  loaded = LoadMemoryImage(empty);
  ASSERT_TRUE(loaded.ok()) << loaded.status();
  EXPECT_TRUE(loaded->empty());
}

// Every truncation, and lengths or string numbers past what is there, are
// DATA_LOSS, never a crash or a huge allocation.
TEST(MemoryImageTest, DamagedImagesAreDataLoss) {
  const std::string bytes = Saved(Clusters());
  for (size_t size = 0; size < bytes.size(); ++size) {
    core::ByteReader in(std::span<const char>(bytes.data(), size));
    absl::StatusOr<std::vector<core::Cluster>> loaded = LoadMemoryImage(in);
    EXPECT_EQ(loaded.status().code(), absl::StatusCode::kDataLoss) << size;
  }
  // Each 4-byte word set to all ones: a count, a length or a string number
  // far past the end, or a value that still decodes.
  for (size_t at = 0; at + 4 <= bytes.size(); at += 4) {
    std::string damaged = bytes;
    damaged.replace(at, 4, std::string(4, '\xff'));
    core::ByteReader in(damaged);
    absl::StatusOr<std::vector<core::Cluster>> loaded = LoadMemoryImage(in);
    EXPECT_TRUE(loaded.ok() ||
                loaded.status().code() == absl::StatusCode::kDataLoss)
        << at << ": " << loaded.status();
  }
  std::string other = bytes;
  other[0] = 'X';
  core::ByteReader in(other);
  EXPECT_EQ(LoadMemoryImage(in).status().code(), absl::StatusCode::kDataLoss);
}

// The fuzzer's seed (make fuzz) is an image: two clusters, an attachment.
TEST(MemoryImageTest, TheFuzzSeedDecodes) {
  std::ifstream file(std::string(FLEETMEM_SOURCE_DIR) +
                         "/services/engine/fuzz_corpus/memory_image_fuzz/"
                         "two_clusters.bin",
                     std::ios::binary);
  ASSERT_TRUE(file.good());
  const std::string bytes((std::istreambuf_iterator<char>(file)),
                          std::istreambuf_iterator<char>());
  core::ByteReader in(bytes);
  absl::StatusOr<std::vector<core::Cluster>> clusters = LoadMemoryImage(in);
  ASSERT_TRUE(clusters.ok()) << clusters.status();
  EXPECT_EQ(in.remaining(), 0u);
  ASSERT_EQ(clusters->size(), 2u);
  EXPECT_EQ((*clusters)[0].traces.size(), 3u);
  EXPECT_EQ((*clusters)[0].traces[1].attachment, "scan");
  EXPECT_EQ((*clusters)[1].traces[0].robot_id, "r2");
}

}  // namespace
}  // namespace fleetmem::engine
