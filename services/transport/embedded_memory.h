// Embedded mode's FleetMemory (fleet_memory.h): one server, its fleets'
// uploads acknowledged at the durable append to their ingest logs and
// applied behind it by engine::WritePath; Consolidate and SampleReplay
// logged and applied there too, as in distributed mode; every call served
// here.
#ifndef FLEETMEM_SERVICES_TRANSPORT_EMBEDDED_MEMORY_H_
#define FLEETMEM_SERVICES_TRANSPORT_EMBEDDED_MEMORY_H_

#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "services/engine/memory_engine.h"
#include "services/engine/write_path.h"
#include "services/transport/fleet_memory.h"

namespace fleetmem::transport {

struct EmbeddedOptions {
  // The write path's backlog bound and appliers.
  engine::WritePathOptions write_path;
  // Consolidate and SampleReplay first wait for the fleet's log to be
  // applied through every upload acknowledged before them; past this they
  // answer UNAVAILABLE (retry) with the backlog, and change nothing.
  absl::Duration max_apply_wait = absl::Seconds(30);
  // The fleet aliases (the server's: engine::StoredAliases over its store);
  // null: a table in memory only (tests). Must outlive the memory.
  engine::AliasTable* aliases = nullptr;
};

// Thread-safe.
class EmbeddedMemory final : public FleetMemory {
 public:
  // Opens the write path over `engine` and the fleets' logs in `log`
  // (recovering them: engine::WritePath::Open). Both must outlive the
  // result.
  static absl::StatusOr<std::unique_ptr<EmbeddedMemory>> Open(
      engine::MemoryEngine* engine, engine::FleetLog* log,
      EmbeddedOptions options = {});
  // Stops the write path (what is not applied yet is, at the next Open).
  ~EmbeddedMemory() override;

  // The write path (backlogs for metrics, Drain at shutdown).
  engine::WritePath& writes() { return *writes_; }

  absl::StatusOr<Uploaded> Upload(std::string_view fleet_id,
                                  std::span<const core::MemoryTrace> traces,
                                  const UploadOptions& options) override;
  // One group commit for all of them (WritePath::AppendMany).
  std::vector<absl::StatusOr<Uploaded>> UploadMany(
      std::string_view fleet_id,
      std::span<const std::span<const core::MemoryTrace>> messages,
      const UploadOptions& options) override;
  absl::StatusOr<engine::ConsolidateResult> Consolidate(
      std::string_view fleet_id) override;
  absl::StatusOr<std::vector<core::MemoryTrace>> SampleReplay(
      std::string_view fleet_id, std::string_view robot_id, uint64_t count,
      std::string_view request_id, const core::ReadFilter* filter) override;
  // Every call (Consolidate, SampleReplay too): the call's record appended
  // to the fleet's log once the uploads before it are applied (CatchUp),
  // and what applying it did (as distributed mode's owner:
  // cluster::Materialiser::Call). The fleet state's refusal as the error.
  absl::StatusOr<engine::AppliedRecord> Call(
      std::string_view fleet_id, const engine::LogRecord& call) override;
  absl::Status CreateFleet(std::string_view fleet_id,
                           const engine::CreateFleetRecord& create) override;
  engine::AliasTable& aliases() override { return *aliases_; }
  engine::Backlog Backlog(std::string_view fleet_id) override;
  absl::StatusOr<std::optional<std::string>> Owner(
      std::string_view fleet_id) override;
  absl::StatusOr<std::vector<std::pair<std::string, std::string>>> Fleets()
      override;
  const std::string& self() const override { return self_; }
  absl::Status Forward(const std::string& address, std::string_view method,
                       const google::protobuf::Message& request,
                       google::protobuf::Message* response,
                       absl::Time deadline) override;
  std::vector<absl::Status> ForwardEach(
      std::span<const std::string> addresses, std::string_view method,
      const google::protobuf::Message& request,
      std::span<google::protobuf::Message* const> responses,
      absl::Time deadline) override;

 private:
  // Waits for the fleet's log to be applied through what was acknowledged
  // so far (max_apply_wait); UNAVAILABLE past it.
  absl::Status CatchUp(std::string_view fleet_id);

  EmbeddedMemory(engine::MemoryEngine* engine,
                 std::unique_ptr<engine::WritePath> writes,
                 EmbeddedOptions options);

  engine::MemoryEngine* const engine_;
  const std::unique_ptr<engine::WritePath> writes_;
  const EmbeddedOptions options_;
  const std::string self_;
  std::unique_ptr<engine::AliasTable> own_aliases_;  // without options.aliases
  engine::AliasTable* aliases_;
};

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_EMBEDDED_MEMORY_H_
