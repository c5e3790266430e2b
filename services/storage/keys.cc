#include "services/storage/keys.h"

#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::storage::keys {
namespace {

void AppendBigEndian(uint64_t value, std::string* out) {
  for (int shift = 56; shift >= 0; shift -= 8) {
    out->push_back(static_cast<char>((value >> shift) & 0xff));
  }
}

std::optional<uint64_t> ReadBigEndian(std::string_view bytes) {
  if (bytes.size() != 8) return std::nullopt;
  uint64_t value = 0;
  for (char c : bytes) value = (value << 8) | static_cast<unsigned char>(c);
  return value;
}

bool IsTag(char c) {
  for (Tag tag : kFleetTags) {
    if (static_cast<char>(tag) == c) return true;
  }
  return c == static_cast<char>(Tag::kLog) ||
         c == static_cast<char>(Tag::kAlias) ||
         c == static_cast<char>(Tag::kSnapshotMark);
}

std::string_view TagName(Tag tag) {
  switch (tag) {
    case Tag::kMeta:
      return "meta";
    case Tag::kPending:
      return "pending";
    case Tag::kCluster:
      return "cluster";
    case Tag::kTrace:
      return "trace";
    case Tag::kCode:
      return "code";
    case Tag::kRobot:
      return "robot";
    case Tag::kEvent:
      return "event";
    case Tag::kLog:
      return "log";
    case Tag::kAlias:
      return "alias";
    case Tag::kSnapshotMark:
      return "mark";
  }
  return "?";
}

std::string KeyWithTraceSuffix(Tag tag, std::string_view fleet_id,
                               const core::TraceKey& key) {
  std::string out = Prefix(tag, fleet_id);
  out.append(key.robot_id);
  out.push_back(kSeparator);
  AppendBigEndian(key.seq, &out);
  return out;
}

std::string KeyWithIdSuffix(Tag tag, std::string_view fleet_id, uint64_t id) {
  std::string out = Prefix(tag, fleet_id);
  AppendBigEndian(id, &out);
  return out;
}

}  // namespace

std::string Prefix(Tag tag, std::string_view fleet_id) {
  std::string out;
  out.reserve(fleet_id.size() + 2);
  out.push_back(static_cast<char>(tag));
  out.append(fleet_id);
  out.push_back(kSeparator);
  return out;
}

std::string PrefixEnd(Tag tag, std::string_view fleet_id) {
  std::string out = Prefix(tag, fleet_id);
  out.back() = static_cast<char>(kSeparator + 1);
  return out;
}

std::string MetaKey(std::string_view fleet_id) {
  return Prefix(Tag::kMeta, fleet_id);
}

std::string AliasKey(std::string_view alias) {
  return Prefix(Tag::kAlias, alias);
}

std::string SnapshotMarkKey(std::string_view fleet_id) {
  return Prefix(Tag::kSnapshotMark, fleet_id);
}

std::string PendingKey(std::string_view fleet_id, const core::TraceKey& key) {
  return KeyWithTraceSuffix(Tag::kPending, fleet_id, key);
}

std::string TraceKey(std::string_view fleet_id, const core::TraceKey& key) {
  return KeyWithTraceSuffix(Tag::kTrace, fleet_id, key);
}

std::string CodeKey(std::string_view fleet_id, const core::TraceKey& key) {
  return KeyWithTraceSuffix(Tag::kCode, fleet_id, key);
}

std::string ClusterKey(std::string_view fleet_id, uint64_t cluster_id) {
  return KeyWithIdSuffix(Tag::kCluster, fleet_id, cluster_id);
}

std::string RobotKey(std::string_view fleet_id, std::string_view robot_id) {
  std::string out = Prefix(Tag::kRobot, fleet_id);
  out.append(robot_id);
  return out;
}

std::string EventKey(std::string_view fleet_id, uint64_t event_id) {
  return KeyWithIdSuffix(Tag::kEvent, fleet_id, event_id);
}

std::string LogKey(std::string_view fleet_id, uint64_t sequence) {
  return KeyWithIdSuffix(Tag::kLog, fleet_id, sequence);
}

std::optional<ParsedKey> Parse(std::string_view key) {
  if (key.empty() || !IsTag(key.front())) return std::nullopt;
  const size_t separator = key.find(kSeparator, 1);
  if (separator == std::string_view::npos) return std::nullopt;
  ParsedKey parsed;
  parsed.tag = static_cast<Tag>(key.front());
  parsed.fleet_id = key.substr(1, separator - 1);
  parsed.suffix = key.substr(separator + 1);
  return parsed;
}

std::optional<core::TraceKey> ParseTraceSuffix(std::string_view suffix) {
  if (suffix.size() < 9 || suffix[suffix.size() - 9] != kSeparator) {
    return std::nullopt;
  }
  const std::string_view robot_id = suffix.substr(0, suffix.size() - 9);
  if (robot_id.find(kSeparator) != std::string_view::npos) return std::nullopt;
  const std::optional<uint64_t> seq =
      ReadBigEndian(suffix.substr(suffix.size() - 8));
  if (!seq) return std::nullopt;
  return core::TraceKey{std::string(robot_id), *seq};
}

std::optional<uint64_t> ParseIdSuffix(std::string_view suffix) {
  return ReadBigEndian(suffix);
}

std::string Describe(std::string_view key) {
  const std::optional<ParsedKey> parsed = Parse(key);
  if (parsed) {
    std::string detail;
    bool ok = true;
    switch (parsed->tag) {
      case Tag::kMeta:
      case Tag::kAlias:
      case Tag::kSnapshotMark:
        ok = parsed->suffix.empty();
        break;
      case Tag::kPending:
      case Tag::kTrace:
      case Tag::kCode: {
        const std::optional<core::TraceKey> trace_key =
            ParseTraceSuffix(parsed->suffix);
        ok = trace_key.has_value();
        if (ok)
          detail = absl::StrCat("/", trace_key->robot_id, "/", trace_key->seq);
        break;
      }
      case Tag::kCluster:
      case Tag::kEvent:
      case Tag::kLog: {
        const std::optional<uint64_t> id = ParseIdSuffix(parsed->suffix);
        ok = id.has_value();
        if (ok) detail = absl::StrCat("/", *id);
        break;
      }
      case Tag::kRobot:
        detail = absl::StrCat("/", V(parsed->suffix));
        break;
    }
    if (ok) {
      return absl::StrCat(V(TagName(parsed->tag)), "[", V(parsed->fleet_id),
                          detail, "]");
    }
  }
  return absl::StrCat("key \"", absl::CHexEscape(V(key)), "\"");
}

}  // namespace fleetmem::storage::keys
