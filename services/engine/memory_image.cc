#include "services/engine/memory_image.h"

#include <cstring>
#include <span>
#include <string>
#include <string_view>
#include <type_traits>
#include <utility>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::engine {
namespace {

constexpr uint32_t kMagic = 0x314d494d;  // "MIM1"
// A trace's fixed part: robot, seq, domain, encoder, place, three rewards,
// timestamp, replay count, attachment length.
constexpr size_t kTraceBytes = 4 + 8 + 4 + 4 + 4 * 8 + 3 * 4 + 8 + 4 + 4;
// A cluster's: id, robot, centroid length, trace count.
constexpr size_t kClusterBytes = 8 + 4 + 4 + 4;
// Longer than any id or version a call accepts.
constexpr size_t kMaxString = 1 << 16;

template <typename T>
void Append(std::string& out, const T& value) {
  static_assert(std::is_trivially_copyable_v<T>);
  out.append(reinterpret_cast<const char*>(&value), sizeof(T));
}

// Numbers each distinct string in the order first met.
class StringTable {
 public:
  uint32_t Add(std::string_view text) {
    auto [it, added] = numbers_.try_emplace(text, strings_.size());
    if (added) strings_.push_back(text);
    return it->second;
  }
  uint32_t Number(std::string_view text) const { return numbers_.at(text); }
  const std::vector<std::string_view>& strings() const { return strings_; }

 private:
  absl::flat_hash_map<std::string_view, uint32_t> numbers_;
  std::vector<std::string_view> strings_;
};

absl::Status Damaged(std::string_view what) {
  return absl::DataLossError(
      absl::StrCat("the index snapshot's memory image ", V(what)));
}

}  // namespace

void SaveMemoryImage(
    const std::map<uint64_t, core::Cluster>& clusters,
    const std::function<std::span<const float>(uint64_t)>& centroid_of,
    core::ByteWriter& out) {
  StringTable table;
  for (const auto& [id, cluster] : clusters) {
    table.Add(cluster.robot_id);
    for (const core::MemoryTrace& trace : cluster.traces) {
      table.Add(trace.robot_id);
      table.Add(trace.domain);
      table.Add(trace.encoder_version);
    }
  }
  // The length first, so that a load can hand the image over without
  // parsing it; counted here rather than by encoding twice.
  uint64_t size = 4 + 4 + 8;
  for (std::string_view text : table.strings()) size += 8 + text.size();
  for (const auto& [id, cluster] : clusters) {
    size += kClusterBytes + centroid_of(id).size() * sizeof(float) +
            cluster.traces.size() * kTraceBytes;
    for (const core::MemoryTrace& trace : cluster.traces) {
      size += trace.attachment.size();
    }
  }
  out.Put<uint64_t>(size);
  out.Put<uint32_t>(kMagic);
  out.Put<uint32_t>(static_cast<uint32_t>(table.strings().size()));
  for (std::string_view text : table.strings()) out.PutString(text);
  out.Put<uint64_t>(clusters.size());
  // A cluster at a time into one buffer: a sink call per field would cost
  // more than the field.
  std::string bytes;
  for (const auto& [id, cluster] : clusters) {
    bytes.clear();
    Append(bytes, cluster.id);
    Append(bytes, table.Number(cluster.robot_id));
    const std::span<const float> centroid = centroid_of(id);
    Append(bytes, static_cast<uint32_t>(centroid.size()));
    bytes.append(reinterpret_cast<const char*>(centroid.data()),
                 centroid.size() * sizeof(float));
    Append(bytes, static_cast<uint32_t>(cluster.traces.size()));
    for (const core::MemoryTrace& trace : cluster.traces) {
      Append(bytes, table.Number(trace.robot_id));
      Append(bytes, trace.seq);
      Append(bytes, table.Number(trace.domain));
      Append(bytes, table.Number(trace.encoder_version));
      Append(bytes, trace.place.x);
      Append(bytes, trace.place.y);
      Append(bytes, trace.place.z);
      Append(bytes, trace.place.yaw);
      Append(bytes, trace.reward);
      Append(bytes, trace.reward_external);
      Append(bytes, trace.reward_internal);
      Append(bytes, trace.timestamp_ns);
      Append(bytes, trace.replay_count);
      Append(bytes, static_cast<uint32_t>(trace.attachment.size()));
      bytes.append(trace.attachment);
    }
    out.PutBytes(bytes.data(), bytes.size());
  }
}

absl::StatusOr<std::vector<core::Cluster>> LoadMemoryImage(
    core::ByteReader& in) {
  uint32_t magic = 0;
  uint32_t string_count = 0;
  if (!in.Get(&magic) || magic != kMagic || !in.Get(&string_count) ||
      string_count > in.remaining() / sizeof(uint64_t)) {
    return Damaged("has a bad header");
  }
  std::vector<std::string> strings(string_count);
  for (std::string& text : strings) {
    if (!in.GetString(&text, kMaxString)) return Damaged("has a bad string");
  }
  auto string_at = [&](uint32_t number, std::string* text) {
    if (number >= strings.size()) return false;
    *text = strings[number];
    return true;
  };
  uint64_t cluster_count = 0;
  if (!in.Get(&cluster_count) ||
      cluster_count > in.remaining() / kClusterBytes) {
    return Damaged("has a bad cluster count");
  }
  std::vector<core::Cluster> clusters(cluster_count);
  for (core::Cluster& cluster : clusters) {
    uint32_t robot = 0;
    uint32_t centroid_size = 0;
    uint32_t trace_count = 0;
    if (!in.Get(&cluster.id) || !in.Get(&robot) ||
        !string_at(robot, &cluster.robot_id) || !in.Get(&centroid_size) ||
        centroid_size > in.remaining() / sizeof(float)) {
      return Damaged("has a bad cluster");
    }
    cluster.centroid.resize(centroid_size);
    if (!in.GetBytes(cluster.centroid.data(), centroid_size * sizeof(float)) ||
        !in.Get(&trace_count) || trace_count > in.remaining() / kTraceBytes) {
      return Damaged(absl::StrCat("has a bad cluster ", cluster.id));
    }
    cluster.traces.resize(trace_count);
    for (core::MemoryTrace& trace : cluster.traces) {
      uint32_t trace_robot = 0;
      uint32_t domain = 0;
      uint32_t encoder = 0;
      uint32_t attachment_size = 0;
      std::span<const char> attachment;
      trace.cluster_id = cluster.id;
      if (!in.Get(&trace_robot) || !string_at(trace_robot, &trace.robot_id) ||
          !in.Get(&trace.seq) || !in.Get(&domain) ||
          !string_at(domain, &trace.domain) || !in.Get(&encoder) ||
          !string_at(encoder, &trace.encoder_version) ||
          !in.Get(&trace.place.x) || !in.Get(&trace.place.y) ||
          !in.Get(&trace.place.z) || !in.Get(&trace.place.yaw) ||
          !in.Get(&trace.reward) || !in.Get(&trace.reward_external) ||
          !in.Get(&trace.reward_internal) || !in.Get(&trace.timestamp_ns) ||
          !in.Get(&trace.replay_count) || !in.Get(&attachment_size) ||
          !in.GetSpan(attachment_size, &attachment)) {
        return Damaged(absl::StrCat("has a bad trace in cluster ", cluster.id));
      }
      trace.attachment.assign(attachment.begin(), attachment.end());
    }
  }
  return clusters;
}

}  // namespace fleetmem::engine
