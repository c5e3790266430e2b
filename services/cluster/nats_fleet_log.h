// The fleet log (engine/fleet_log.h), the lease table and the snapshot
// store (cluster_ports.h) on NATS JetStream (Debian's libnats, nats.c):
//  - each fleet's log is a stream, FLEETMEM_<XXH3-64 of the fleet id in
//    hex> on subject fleetmem.log.<same>, replicated `replicas` times, with
//    JetStream's deduplication by message id (Nats-Msg-Id) over
//    `duplicate_window`; the fleet id is the stream's description, checked
//    on use, so two ids with one hash cannot share a log;
//  - each fleet's snapshots are a second stream, FLEETMEM_SNAP_<same>:
//    an image in chunks on fleetmem.snap.<same>.chunk, then its description
//    (log_record.proto's SnapshotMeta) on fleetmem.snap.<same>.meta,
//    published only if the meta subject has not changed since it was read
//    (so of two replicas storing snapshots at once one wins); the stream is
//    then purged below the new image's first chunk;
//  - leases are keys of one key-value bucket whose entries expire after
//    `lease_ttl` unless renewed: Acquire creates the key (only if absent),
//    Renew and Release update or delete it only at the revision the lease
//    holds, so a replica that lost its lease cannot renew it; each
//    replica's announcement (Announce) is a key of the same bucket,
//    replica.<hash of its id>, listed from the bucket's stream state
//    (no consumer).
// Thread-safe: nats.c connections and JetStream contexts are.
#ifndef FLEETMEM_SERVICES_CLUSTER_NATS_FLEET_LOG_H_
#define FLEETMEM_SERVICES_CLUSTER_NATS_FLEET_LOG_H_

#include <memory>
#include <optional>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "services/cluster/cluster_ports.h"
#include "services/engine/fleet_aliases.h"
#include "services/engine/fleet_log.h"

namespace fleetmem::cluster {

struct NatsOptions {
  // nats://HOST:PORT (tls://… with TLS), at least one.
  std::vector<std::string> servers;
  // A NATS credentials file (user JWT and nkey seed); empty: none.
  std::string credentials_file;
  // TLS to NATS: the CA bundle to trust (setting it turns TLS on), and a
  // client certificate and key (both or neither).
  std::string ca_file;
  std::string cert_file;
  std::string key_file;
  // Copies of each fleet's stream and of the lease bucket (3 in production;
  // at most the number of NATS servers).
  int replicas = 3;
  // JetStream drops a repeat of a message id within this window.
  absl::Duration duplicate_window = absl::Minutes(2);
  // A lease not renewed within this time is free: a dead owner's fleets
  // are taken over after at most this long (plus a round of the takers'
  // loop and the catch-up), inside the 10 s the design allows.
  absl::Duration lease_ttl = absl::Seconds(5);
  // Each request to NATS (publish acknowledgement, stream and key
  // operations, reads) waits at most this long.
  absl::Duration timeout = absl::Seconds(5);
  // The lease bucket.
  std::string lease_bucket = "fleetmem-leases";
  // The fleet aliases' bucket (no time-to-live; nats_aliases.h).
  std::string alias_bucket = "fleetmem-aliases";
};

// INVALID_ARGUMENT naming the first bad field.
absl::Status ValidateNatsOptions(const NatsOptions& options);

class NatsFleetLog final : public engine::FleetLog,
                           public LeaseTable,
                           public SnapshotStore {
 public:
  // Connects and makes the lease bucket if missing. UNAVAILABLE when no
  // server answers; the error of the first failing step otherwise.
  static absl::StatusOr<std::unique_ptr<NatsFleetLog>> Connect(
      NatsOptions options);
  ~NatsFleetLog() override;

  // Publishes the entries in order (the log's stream made on first use),
  // each under its id (Nats-Msg-Id; none for an empty id), without waiting
  // for one's acknowledgement before publishing the next (a write path's
  // group costs about one round trip, not one per entry), and returns once
  // JetStream stored each on its replicas. An only_first entry is
  // published, and acknowledged, before the rest. On error the status says
  // which of the entries the log holds (by position from 1); UNAVAILABLE or
  // DEADLINE_EXCEEDED: unknown whether those that failed were stored;
  // appending again under the same ids cannot store one twice within the
  // duplicate window. options.above must be 0.
  absl::StatusOr<std::vector<engine::AppendedEntry>> Append(
      std::string_view fleet_id, std::span<const engine::LogAppend> entries,
      const engine::AppendOptions& options) override;
  // One get per entry from the stream's leader; numbers the stream skipped
  // are passed (said in the log). OUT_OF_RANGE when entries after `after`
  // were trimmed.
  absl::StatusOr<std::vector<engine::LogEntry>> Read(std::string_view fleet_id,
                                                     uint64_t after,
                                                     size_t max) override;
  absl::StatusOr<engine::LogBounds> Bounds(std::string_view fleet_id) override;
  // Purges the stream through `through` (entries a snapshot covers).
  absl::Status Trim(std::string_view fleet_id, uint64_t through) override;
  // While JetStream cannot list the logs (electing its meta leader), those
  // it listed before, if any.
  absl::StatusOr<std::vector<std::string>> Fleets() override;

  absl::Status Put(std::string_view fleet_id, const SnapshotInfo& info,
                   std::string_view image) override;
  absl::StatusOr<std::optional<SnapshotInfo>> Latest(
      std::string_view fleet_id) override;
  absl::StatusOr<std::optional<std::pair<SnapshotInfo, std::string>>> Fetch(
      std::string_view fleet_id) override;

  absl::StatusOr<Lease> Acquire(std::string_view fleet_id,
                                std::string_view owner) override;
  absl::StatusOr<Lease> Renew(const Lease& lease) override;
  absl::Status Release(const Lease& lease) override;
  absl::StatusOr<std::optional<Lease>> Holder(
      std::string_view fleet_id) override;
  absl::Status Announce(std::string_view replica, uint64_t fleets) override;

  // The fleet aliases every replica shares (nats_aliases.h), read when the
  // log connected.
  engine::AliasTable& aliases();
  absl::StatusOr<std::vector<std::pair<std::string, uint64_t>>> Replicas()
      override;

 private:
  struct Handles;  // nats.c's, kept out of this header
  NatsFleetLog(NatsOptions options, std::unique_ptr<Handles> handles);
  // Makes the fleet's stream if missing (once per fleet and process);
  // FAILED_PRECONDITION if the stream of its hash holds another fleet.
  absl::Status EnsureStream(std::string_view fleet_id);
  // The same for the fleet's snapshot stream.
  absl::Status EnsureSnapshotStream(std::string_view fleet_id);
  // Makes stream `name` on `subject_pattern` if missing, described by the
  // fleet id; `is_log` denies deleting single messages.
  absl::Status EnsureFleetStream(std::string_view fleet_id,
                                 const std::string& name,
                                 const std::string& subject_pattern,
                                 bool is_log);
  // Removes the messages of `stream` before `sequence` (none if there are
  // none before it).
  absl::Status PurgeBelow(const std::string& stream, uint64_t sequence);
  // Append's entries after the first, published without waiting for each
  // acknowledgement; `data` their encodings.
  absl::StatusOr<std::vector<engine::AppendedEntry>> AppendPipelined(
      std::string_view fleet_id, std::span<const engine::LogAppend> entries,
      std::span<const std::string> data);
  // Appends one entry (Append's), as the log's first if `only_first`.
  absl::StatusOr<engine::AppendedEntry> AppendOne(std::string_view fleet_id,
                                                  std::string_view id,
                                                  std::string_view data,
                                                  bool only_first);
  // The latest snapshot's description and the stream sequence of its
  // message (nullopt: none).
  struct LatestMeta;
  absl::StatusOr<std::optional<LatestMeta>> ReadMeta(std::string_view fleet_id);

  const NatsOptions options_;
  std::unique_ptr<Handles> handles_;
  std::unique_ptr<engine::AliasTable> aliases_;  // uses handles_
};

// The stream and subject of a fleet's log, and the key of its lease.
std::string FleetStreamName(std::string_view fleet_id);
std::string FleetSubject(std::string_view fleet_id);
std::string FleetLeaseKey(std::string_view fleet_id);
std::string SnapshotStreamName(std::string_view fleet_id);

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_NATS_FLEET_LOG_H_
