// Key layout of the RocksDB store. Internal to services/storage.
//
// Every key is  tag (1 byte) | fleet id | 0x00 | suffix, with suffix:
//   meta     'm'  (empty)
//   pending  'p'  robot id | 0x00 | seq (8 bytes, big-endian)
//   cluster  'c'  cluster id (8 bytes, big-endian)
//   trace    't'  robot id | 0x00 | seq (8 bytes, big-endian)
//   code     'k'  robot id | 0x00 | seq: the code of the trace under 't'
//                 with the same suffix, apart from its other fields (so
//                 that a restart whose index snapshot holds the codes reads
//                 ~150 bytes a trace, not ~1,200; layout 2)
//   robot    'r'  robot id
//   event    'e'  event id (8 bytes, big-endian)
//   log      'l'  sequence (8 bytes, big-endian): the ingest log, apart
//                 from the fleet's state (not in kFleetTags)
//   mark     's'  (empty); the value is the id (stamp, checksum) of the
//                 fleet's index snapshot, put when it is saved and deleted
//                 by the fleet's next write: while it is here and names
//                 the file on disk, that snapshot describes the fleet's
//                 state exactly (not in kFleetTags)
// and one kind whose id is an alias, not a fleet's (not in kFleetTags):
//   alias    'a'  (empty); the value is the fleet id it names
// Ids are restricted upstream to [A-Za-z0-9._:-], so 0x00 never occurs in
// them: all keys of one (tag, fleet) form one contiguous range, a fleet id
// that is a prefix of another ("f", "f1") cannot alias it, and big-endian
// numbers sort numerically. Two more keys belong to no fleet: kFormatKey
// holds the layout version; kClosedKey the store's latest sequence number
// before a clean close wrote it (a start that finds the sequence one past
// it knows that nothing, no older build either, wrote since: the marks
// hold).
#ifndef FLEETMEM_SERVICES_STORAGE_KEYS_H_
#define FLEETMEM_SERVICES_STORAGE_KEYS_H_

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "services/core/types.h"

namespace fleetmem::storage::keys {

enum class Tag : char {
  kMeta = 'm',
  kPending = 'p',
  kCluster = 'c',
  kTrace = 't',
  kCode = 'k',
  kRobot = 'r',
  kEvent = 'e',
  kLog = 'l',
  kAlias = 'a',
  kSnapshotMark = 's',
};

// Every tag that holds a fleet's state (not its ingest log).
inline constexpr Tag kFleetTags[] = {Tag::kMeta,  Tag::kPending, Tag::kCluster,
                                     Tag::kTrace, Tag::kCode,    Tag::kRobot,
                                     Tag::kEvent};

inline constexpr char kSeparator = '\0';
inline constexpr std::string_view kFormatKey = "!format";
// Layout 2 keeps a static-memory trace's code under its own key ('k');
// layout 1 kept it inside the trace record. A store of layout 1 is
// migrated when it opens (rocksdb_store.cc: MigrateCodes).
inline constexpr std::string_view kFormatVersion = "fleetmem.storage/2";
inline constexpr std::string_view kFormatVersion1 = "fleetmem.storage/1";
inline constexpr std::string_view kClosedKey = "!closed";

// tag | fleet | 0x00: every key of (tag, fleet) starts with it.
std::string Prefix(Tag tag, std::string_view fleet_id);
// tag | fleet | 0x01: the first key after every key of (tag, fleet).
std::string PrefixEnd(Tag tag, std::string_view fleet_id);

std::string MetaKey(std::string_view fleet_id);
std::string PendingKey(std::string_view fleet_id, const core::TraceKey& key);
std::string TraceKey(std::string_view fleet_id, const core::TraceKey& key);
std::string CodeKey(std::string_view fleet_id, const core::TraceKey& key);
std::string ClusterKey(std::string_view fleet_id, uint64_t cluster_id);
std::string RobotKey(std::string_view fleet_id, std::string_view robot_id);
std::string EventKey(std::string_view fleet_id, uint64_t event_id);
std::string LogKey(std::string_view fleet_id, uint64_t sequence);
std::string AliasKey(std::string_view alias);
std::string SnapshotMarkKey(std::string_view fleet_id);

// The parts of a key; nullopt if `key` does not follow the layout.
struct ParsedKey {
  Tag tag = Tag::kMeta;
  std::string_view fleet_id;
  std::string_view suffix;  // after the separator
};
std::optional<ParsedKey> Parse(std::string_view key);

// Suffix decoders; nullopt if malformed.
std::optional<core::TraceKey> ParseTraceSuffix(std::string_view suffix);
std::optional<uint64_t> ParseIdSuffix(std::string_view suffix);

// A readable name for error messages: "trace[f1/r2/17]", "cluster[f1/5]",
// "meta[f1]"; an unparsable key is shown escaped.
std::string Describe(std::string_view key);

}  // namespace fleetmem::storage::keys

#endif  // FLEETMEM_SERVICES_STORAGE_KEYS_H_
