#include "services/transport/embedded_memory.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::transport {

namespace {

// An embedded server serves every fleet itself.
absl::Status NothingToForward(const std::string& address,
                              std::string_view method) {
  return absl::InternalError(absl::StrCat(
      "an embedded server serves every fleet itself; asked to forward ",
      V(method), " to \"", address, "\""));
}

}  // namespace

absl::StatusOr<std::unique_ptr<EmbeddedMemory>> EmbeddedMemory::Open(
    engine::MemoryEngine* engine, engine::FleetLog* log,
    EmbeddedOptions options) {
  if (options.max_apply_wait <= absl::ZeroDuration()) {
    return absl::InvalidArgumentError("max_apply_wait must be positive");
  }
  absl::StatusOr<std::unique_ptr<engine::WritePath>> writes =
      engine::WritePath::Open(options.write_path, engine, log);
  if (!writes.ok()) return writes.status();
  return std::unique_ptr<EmbeddedMemory>(
      new EmbeddedMemory(engine, *std::move(writes), std::move(options)));
}

EmbeddedMemory::EmbeddedMemory(engine::MemoryEngine* engine,
                               std::unique_ptr<engine::WritePath> writes,
                               EmbeddedOptions options)
    : engine_(engine),
      writes_(std::move(writes)),
      options_(std::move(options)),
      own_aliases_(options_.aliases == nullptr
                       ? *engine::StoredAliases::Open(nullptr)
                       : nullptr),
      aliases_(options_.aliases != nullptr ? options_.aliases
                                           : own_aliases_.get()) {}

EmbeddedMemory::~EmbeddedMemory() { writes_->Stop(); }

absl::StatusOr<Uploaded> EmbeddedMemory::Upload(
    std::string_view fleet_id, std::span<const core::MemoryTrace> traces,
    const UploadOptions& options) {
  const std::span<const core::MemoryTrace> messages[] = {traces};
  return std::move(UploadMany(fleet_id, messages, options).front());
}

std::vector<absl::StatusOr<Uploaded>> EmbeddedMemory::UploadMany(
    std::string_view fleet_id,
    std::span<const std::span<const core::MemoryTrace>> messages,
    const UploadOptions& options) {
  std::vector<absl::StatusOr<engine::Appended>> appended =
      writes_->AppendMany(fleet_id, messages, options.wait_applied);
  std::vector<absl::StatusOr<Uploaded>> results;
  results.reserve(appended.size());
  for (absl::StatusOr<engine::Appended>& one : appended) {
    if (!one.ok()) {
      results.push_back(one.status());
      continue;
    }
    Uploaded uploaded;
    uploaded.result.accepted = one->accepted;
    uploaded.result.duplicates = one->duplicates;
    uploaded.sequence = one->sequence;
    if (options.wait_applied) {
      absl::Status waited =
          writes_->WaitApplied(fleet_id, one->sequence, options.deadline);
      if (!waited.ok()) {
        // Durable, and applied later: the client must not store it again
        // as if it were lost, but needs to know it did not wait.
        results.push_back(
            absl::Status(waited.code(),
                         absl::StrCat(waited.message(), " (", one->accepted,
                                      " traces of this message are durable and "
                                      "acknowledged)")));
        continue;
      }
      if (one->applied != nullptr) {
        if (!one->applied->refused.ok()) {
          results.push_back(one->applied->refused);
          continue;
        }
        uploaded.result.consolidations = one->applied->consolidations;
      }
      uploaded.applied = true;
    }
    results.push_back(std::move(uploaded));
  }
  return results;
}

absl::Status EmbeddedMemory::CatchUp(std::string_view fleet_id) {
  absl::Status waited =
      writes_->WaitAppliedAll(fleet_id, absl::Now() + options_.max_apply_wait);
  if (absl::IsDeadlineExceeded(waited)) {
    return absl::UnavailableError(
        absl::StrCat("fleet \"", V(fleet_id),
                     "\": the uploads acknowledged before this "
                     "call are not all applied after ",
                     absl::FormatDuration(options_.max_apply_wait), " (",
                     waited.message(), "); nothing was changed: retry"));
  }
  return waited;
}

absl::StatusOr<engine::AppliedRecord> EmbeddedMemory::Call(
    std::string_view fleet_id, const engine::LogRecord& call) {
  // The uploads before it applied first, so that a call that cannot be
  // served soon is refused with nothing logged.
  if (absl::Status caught_up = CatchUp(fleet_id); !caught_up.ok()) {
    return caught_up;
  }
  absl::StatusOr<engine::Appended> logged = writes_->AppendCall(fleet_id, call);
  if (!logged.ok()) return logged.status();
  absl::Status applied = writes_->WaitApplied(
      fleet_id, logged->sequence, absl::Now() + options_.max_apply_wait);
  if (!applied.ok()) {
    return absl::Status(
        applied.code(),
        absl::StrCat(applied.message(),
                     "; the call is logged and is applied after the entries "
                     "before it (a sample retried with the same request_id "
                     "gets its traces)"));
  }
  if (!logged->applied->refused.ok()) return logged->applied->refused;
  return *logged->applied;
}

absl::Status EmbeddedMemory::CreateFleet(
    std::string_view fleet_id, const engine::CreateFleetRecord& create) {
  absl::StatusOr<engine::Appended> logged =
      writes_->AppendCreate(fleet_id, create);
  if (!logged.ok()) return logged.status();
  absl::Status applied = writes_->WaitApplied(
      fleet_id, logged->sequence, absl::Now() + options_.max_apply_wait);
  if (!applied.ok()) {
    return absl::Status(applied.code(),
                        absl::StrCat(applied.message(),
                                     "; the fleet's creation is logged and "
                                     "is applied in a moment"));
  }
  return logged->applied->refused;
}

absl::StatusOr<engine::ConsolidateResult> EmbeddedMemory::Consolidate(
    std::string_view fleet_id) {
  absl::StatusOr<engine::AppliedRecord> applied =
      Call(fleet_id, engine::ConsolidateRecord{});
  if (!applied.ok()) return applied.status();
  return applied->consolidated;
}

absl::StatusOr<std::vector<core::MemoryTrace>> EmbeddedMemory::SampleReplay(
    std::string_view fleet_id, std::string_view robot_id, uint64_t count,
    std::string_view request_id, const core::ReadFilter* filter) {
  if (absl::Status valid = engine_->CheckSampleReplay(fleet_id, robot_id, count,
                                                      request_id, filter);
      !valid.ok()) {
    return valid;
  }
  absl::StatusOr<engine::AppliedRecord> applied =
      Call(fleet_id,
           engine::SampleReplayRecord{robot_id, count, request_id, filter});
  if (!applied.ok()) return applied.status();
  return std::move(applied->sample);
}

engine::Backlog EmbeddedMemory::Backlog(std::string_view fleet_id) {
  return writes_->GetBacklog(fleet_id);
}

absl::StatusOr<std::optional<std::string>> EmbeddedMemory::Owner(
    std::string_view) {
  return std::nullopt;
}

absl::StatusOr<std::vector<std::pair<std::string, std::string>>>
EmbeddedMemory::Fleets() {
  std::vector<std::pair<std::string, std::string>> fleets;
  for (std::string& fleet_id : engine_->ListFleets()) {
    fleets.emplace_back(std::move(fleet_id), self_);
  }
  return fleets;
}

absl::Status EmbeddedMemory::Forward(const std::string& address,
                                     std::string_view method,
                                     const google::protobuf::Message&,
                                     google::protobuf::Message*, absl::Time) {
  return NothingToForward(address, method);
}

std::vector<absl::Status> EmbeddedMemory::ForwardEach(
    std::span<const std::string> addresses, std::string_view method,
    const google::protobuf::Message&,
    std::span<google::protobuf::Message* const>, absl::Time) {
  std::vector<absl::Status> statuses;
  for (const std::string& address : addresses) {
    statuses.push_back(NothingToForward(address, method));
  }
  return statuses;
}

}  // namespace fleetmem::transport
