// fleetmem-server's distributed mode (docs/distributed.md) as the
// transport's FleetMemory (services/transport/fleet_memory.h): the
// connection to NATS JetStream, this replica's ownership loop (ClusterNode),
// uploads forwarded to their fleet's owner, which admits and appends them
// through the same write path as embedded mode (engine::WritePath, over
// the replicated log) and applies the log with the same applier
// (engine::LogApplier, run by Materialiser under the lease), calls served
// by the owner of their fleet (forwarded there by PeerForwarder),
// Consolidate and SampleReplay through the log.
#ifndef FLEETMEM_SERVICES_CLUSTER_REPLICATED_MEMORY_H_
#define FLEETMEM_SERVICES_CLUSTER_REPLICATED_MEMORY_H_

#include <functional>
#include <memory>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "services/cluster/cluster_node.h"
#include "services/cluster/materialiser.h"
#include "services/cluster/nats_fleet_log.h"
#include "services/engine/admission.h"
#include "services/engine/memory_engine.h"
#include "services/engine/upload_quota.h"
#include "services/engine/write_path.h"
#include "services/transport/fleet_memory.h"
#include "services/transport/peer_forwarder.h"

namespace fleetmem::cluster {

class ReplicatedMemory final : public transport::FleetMemory {
 public:
  // `self`: this replica's advertised address; `max_entry_bytes`: the
  // largest log entry (under NATS's max_payload); `max_backlog_traces`:
  // the bound on a fleet's acknowledged, unapplied traces its owner admits
  // (write_path.max_backlog_traces, as in embedded mode; 0: none);
  // `rates`: the upload rate limits this replica applies to what it
  // receives (the engine applying the log runs without them). `engine`
  // must outlive the object.
  ReplicatedMemory(std::string self, size_t max_entry_bytes,
                   uint64_t max_backlog_traces, engine::QuotaOptions rates,
                   std::unique_ptr<NatsFleetLog> log,
                   transport::PeerOptions peers, engine::MemoryEngine* engine,
                   ClusterNodeOptions node);
  // Stops the loop and hands this replica's fleets over (Shutdown).
  ~ReplicatedMemory() override;

  // Starts the ownership loop; `lost` is called for each fleet this
  // replica stops owning (its watches end; its write path ends before).
  void Run(std::function<void(const std::string&)> lost = nullptr);
  // Stops the loop and releases every lease, so that the other replicas
  // take this one's fleets at once (a clean shutdown).
  void Shutdown();

  // The receiving replica checks the upload's shape and rates it, then
  // forwards it to the fleet's owner, whose write path admits it as
  // embedded mode's does (engine::WritePath: shape, de-duplication by
  // (robot, seq) against what the fleet holds and its log's unapplied
  // tail, max_traces_per_fleet, the backlog bound) and appends it; a new
  // fleet (max_fleets) is created by the replica that receives its first
  // upload (Ingest). Acknowledged once the log holds the upload on its
  // replicas; options.wait_applied is not served (the answer's `applied`
  // is false). UNAVAILABLE (retry) while the fleet has no owner.
  absl::StatusOr<transport::Uploaded> Upload(
      std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
      const transport::UploadOptions& options) override;
  // At the fleet's owner, a stream's waiting messages are checked and rated
  // one by one (the first refused ends the call: the rest ABORTED), then
  // written in one group commit of its write path; elsewhere Upload one
  // after another (FleetMemory::UploadMany).
  std::vector<absl::StatusOr<transport::Uploaded>> UploadMany(
      std::string_view fleet_id,
      std::span<const std::span<const core::MemoryTrace>> messages,
      const transport::UploadOptions& options) override;
  // Entries of the fleet's log not applied yet, for a fleet owned here (one
  // call to NATS); zeros for the others.
  // Shared by every replica: the log's bucket (nats_aliases.h).
  engine::AliasTable& aliases() override { return log_->aliases(); }
  engine::Backlog Backlog(std::string_view fleet_id) override;
  absl::StatusOr<std::optional<std::string>> Owner(
      std::string_view fleet_id) override;
  absl::StatusOr<std::vector<std::pair<std::string, std::string>>> Fleets()
      override;
  const std::string& self() const override { return self_; }
  // Entries of each owned fleet's log not applied yet (one call to NATS
  // per fleet; a fleet whose log cannot be read now is left out).
  std::vector<std::pair<std::string, double>> LogLag();
  // Fleets that have a log, and fleets owned here, as of the last round.
  std::pair<double, double> FleetCounts() const {
    return {static_cast<double>(node_.fleets_seen()),
            static_cast<double>(node_.owned().size())};
  }
  // True if this replica holds the fleet's lease (as of its last round);
  // no call to NATS.
  bool Serves(std::string_view fleet_id) {
    return node_.materialiser().Owns(fleet_id);
  }
  absl::Status Forward(const std::string& address, std::string_view method,
                       const google::protobuf::Message& request,
                       google::protobuf::Message* response,
                       absl::Time deadline) override;
  std::vector<absl::Status> ForwardEach(
      std::span<const std::string> addresses, std::string_view method,
      const google::protobuf::Message& request,
      std::span<google::protobuf::Message* const> responses,
      absl::Time deadline) override;
  absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id) override;
  absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view request_id, const core::ReadFilter* filter) override;
  absl::StatusOr<engine::AppliedRecord> Call(
      std::string_view fleet_id, const engine::LogRecord& call) override;
  // Appended by the receiving replica as the fleet's log's first entry
  // (as a first upload is: Create), then taken here if no replica owns
  // the fleet, and applied.
  absl::Status CreateFleet(std::string_view fleet_id,
                           const engine::CreateFleetRecord& create) override;

 private:
  // The last holder read for each fleet: used while the lease table cannot
  // be read (NATS electing a leader), so that reads go on.
  absl::Mutex owners_mu_;
  absl::flat_hash_map<std::string, std::string> last_owner_
      ABSL_GUARDED_BY(owners_mu_);
  // The fleets of the last listing that NATS answered.
  std::vector<std::string> known_fleets_ ABSL_GUARDED_BY(owners_mu_);

  // The shape of each fleet, read from the first entry of its log (it
  // changes only when the fleet is deleted and made anew: read again,
  // `fresh`, where a shape does not fit).
  absl::flat_hash_map<std::string, engine::FleetShape> shapes_
      ABSL_GUARDED_BY(owners_mu_);
  // What uploads to the fleet must match: its first upload's, from its
  // log (after a DeleteFleet's snapshot, the first entry since); nullopt
  // for a fleet without a log (this upload fixes it). `fresh`: not the
  // shape read before.
  absl::StatusOr<std::optional<engine::FleetShape>> ShapeOf(
      std::string_view fleet_id, bool fresh = false);

  // `node` with the Materialiser's calls appended through writes_.
  ClusterNodeOptions WithCallsThroughTheWritePath(ClusterNodeOptions node);
  // A fleet's first upload, by the replica that receives it (Ingest).
  // FAILED_PRECONDITION: another upload created the fleet meanwhile.
  absl::StatusOr<transport::Uploaded> Create(
      std::string_view fleet_id, std::span<const core::MemoryTrace> traces);
  // Uploads to a fleet owned here, through the write path (one group
  // commit): one result each.
  std::vector<absl::StatusOr<transport::Uploaded>> Write(
      std::string_view fleet_id,
      std::span<const std::span<const core::MemoryTrace>> messages);
  // UNAVAILABLE for a fleet this replica holds (or is taking) but whose
  // log before the take is not applied yet (`progress`; nullopt while the
  // take itself runs).
  absl::Status Catching(
      std::string_view fleet_id,
      const std::optional<Materialiser::TakeProgress>& progress);
  // Forwards an upload to the fleet's owner, `holder` (as TakeIfFree read
  // it; empty: looked up) (once: a forwarded upload that meets no owner
  // here is UNAVAILABLE).
  absl::StatusOr<transport::Uploaded> ForwardUpload(
      std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
      const transport::UploadOptions& options, const std::string& holder);
  // Takes the fleet's lease if no replica holds it; true if this replica
  // holds it then. Otherwise `holder` gets the replica that holds it, if
  // the lease table could say (one read of it per upload).
  bool TakeIfFree(std::string_view fleet_id, std::string* holder);

  const std::string self_;
  const size_t max_entry_bytes_;
  // Upload rates (limits.*_per_second), applied by the replica that
  // receives an upload, per replica: a robot uploading through several
  // replicas gets each one's rate. The engine applying the log runs
  // without them.
  engine::UploadQuota rates_;
  engine::MemoryEngine* const engine_;
  std::unique_ptr<NatsFleetLog> log_;
  // The write path of the fleets owned here: admission and group commit as
  // in embedded mode, over the replicated log; the Materialiser applies.
  std::unique_ptr<engine::WritePath> writes_;
  transport::PeerForwarder forwarder_;
  ClusterNode node_;
  bool shut_down_ = false;
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_REPLICATED_MEMORY_H_
