// The transport's one seam between the calls it serves and the mode the
// server runs in (docs/architecture.md): where an upload goes and when it is
// acknowledged, how Consolidate and SampleReplay are applied, which replica
// serves a fleet's calls. Picked once, in main.cc:
//   - embedded (EmbeddedMemory, embedded_memory.h): one server; uploads are
//     acknowledged at the durable append to the fleet's ingest log in its
//     RocksDB and applied behind it (engine::WritePath); every fleet is
//     served here;
//   - replicated (cluster::ReplicatedMemory, services/cluster): uploads
//     are acknowledged at the append to the fleet's replicated log
//     (JetStream) and applied by the fleet's owner; calls are served by the
//     owner, forwarded there by the others.
// Both apply a fleet's log through the same MemoryEngine::Upload with the
// entry's sequence.
#ifndef FLEETMEM_SERVICES_TRANSPORT_FLEET_MEMORY_H_
#define FLEETMEM_SERVICES_TRANSPORT_FLEET_MEMORY_H_

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "google/protobuf/message.h"
#include "services/core/types.h"
#include "services/engine/fleet_aliases.h"
#include "services/engine/memory_engine.h"
#include "services/engine/write_path.h"

namespace fleetmem::transport {

struct UploadOptions {
  // Return once the upload is applied (consolidated where it fills a
  // segment, and searchable), not only durable; the result then counts the
  // consolidations it triggered. Read-your-writes for the callers that need
  // it; uploads are acknowledged at the durable append otherwise.
  bool wait_applied = false;
  absl::Time deadline = absl::InfiniteFuture();
  // Forwarded by another replica (distributed mode): admitted there but
  // for the fleet's load, which is this replica's to admit; not forwarded
  // again.
  bool forwarded = false;
};

// What an upload did.
struct Uploaded {
  engine::UploadResult result;
  // The sequence of the fleet's log entry holding the last accepted trace
  // (0: none accepted). GetStats' applied_through reaching it means the
  // upload is applied.
  uint64_t sequence = 0;
  // The upload was applied before the answer (wait_applied, where the mode
  // supports it).
  bool applied = false;
};

// Thread-safe.
class FleetMemory {
 public:
  virtual ~FleetMemory() = default;

  // Validates an upload (once) and makes it durable in the fleet's log;
  // returns then, or once applied with options.wait_applied. `accepted`
  // counts the traces appended, `duplicates` those the fleet had received
  // (or, replicated, those of log entries it already held).
  virtual absl::StatusOr<Uploaded> Upload(
      std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
      const UploadOptions& options) = 0;
  // Upload for the messages of one stream that arrived while the earlier
  // ones were stored: one result each, in order. The mode may store them
  // together (embedded: one group commit); by default one after another,
  // stopping at the first refusal (the rest then get ABORTED, nothing of
  // them stored).
  virtual std::vector<absl::StatusOr<Uploaded>> UploadMany(
      std::string_view fleet_id,
      std::span<const std::span<const core::MemoryTrace>> messages,
      const UploadOptions& options);

  // The calls that change memory besides uploads, applied after every
  // upload acknowledged before them.
  virtual absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id) = 0;
  // `filter` (null: any trace) travels in the call's log record.
  virtual absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view request_id, const core::ReadFilter* filter) = 0;

  // CreateFleet (arguments checked by the caller: MemoryEngine::
  // CheckCreateFleet): the record made the fleet's first log entry, and
  // applied (embedded) or taken to be applied by the owner (distributed).
  // ALREADY_EXISTS when the fleet exists (by CreateFleet or an upload).
  virtual absl::Status CreateFleet(std::string_view fleet_id,
                                   const engine::CreateFleetRecord& create) = 0;

  // Any other call that changes memory (DeleteTraces, UpdateRewards: every
  // record but an upload's), its arguments checked by the caller: its
  // record logged after every upload acknowledged before it and applied
  // through; what applying it did. The fleet state's refusal as the error
  // (AppliedRecord::refused).
  virtual absl::StatusOr<engine::AppliedRecord> Call(
      std::string_view fleet_id, const engine::LogRecord& call) = 0;

  // The fleet aliases of this mode (engine/fleet_aliases.h): embedded, in
  // the store; distributed, shared by every replica.
  virtual engine::AliasTable& aliases() = 0;

  // The fleet's acknowledged uploads not applied yet, as this server sees
  // them (GetStats, /metrics).
  virtual engine::Backlog Backlog(std::string_view fleet_id) = 0;

  // Where the fleet's calls are served: nullopt for this server (always,
  // embedded), else the owner's address. UNAVAILABLE when no replica holds
  // the fleet right now (an owner was lost and its lease has not expired).
  virtual absl::StatusOr<std::optional<std::string>> Owner(
      std::string_view fleet_id) = 0;
  // The fleets, and the address of the server that serves each (self():
  // this one; empty: none now).
  virtual absl::StatusOr<std::vector<std::pair<std::string, std::string>>>
  Fleets() = 0;
  // This server's address among its replicas (empty, embedded).
  virtual const std::string& self() const = 0;

  // Calls the unary `method` ("QueryPlace") of fleetmem.v1.MemoryService
  // on the replica at `address` (an Owner), marked as forwarded (that
  // replica serves it or answers UNAVAILABLE; it never forwards it again),
  // given up at `deadline` (the caller's) or the mode's own limit on a
  // forwarded call, whichever is first.
  virtual absl::Status Forward(const std::string& address,
                               std::string_view method,
                               const google::protobuf::Message& request,
                               google::protobuf::Message* response,
                               absl::Time deadline) = 0;
  // Forward to several replicas at once (ListFleets' fan-out): one status
  // per address, in order, each response filled where OK; returns by
  // `deadline` whatever some replicas did not answer.
  virtual std::vector<absl::Status> ForwardEach(
      std::span<const std::string> addresses, std::string_view method,
      const google::protobuf::Message& request,
      std::span<google::protobuf::Message* const> responses,
      absl::Time deadline) = 0;
};

// Retention (docs/api.md): for each fleet served here whose settings bound
// its traces' age or number per robot, a retention call as of `now_ns`
// through the fleet's log (FleetMemory::Call), so that every replica
// deletes the same traces. The traces deleted in all; a fleet's error is
// logged and the others go on. A server's periodic task.
uint64_t EnforceRetention(engine::MemoryEngine& engine, FleetMemory& memory,
                          int64_t now_ns);

// The metadata key that marks a forwarded call.
inline constexpr char kForwardedHeader[] = "x-fleetmem-forwarded";

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_FLEET_MEMORY_H_
