// MemoryApi's alias calls (memory_api.h; engine/fleet_aliases.h).
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "services/core/validation.h"
#include "services/transport/memory_api.h"

namespace fleetmem::transport {
namespace {

// The caller may point aliases (an admin), and at what: a valid name that
// is a fleet, not an alias; the alias a valid name that is no fleet's.
absl::Status CheckAliasTarget(const auth::Principal& caller,
                              FleetMemory& memory, const std::string& alias,
                              const std::string& fleet_id) {
  absl::Status valid = auth::Authorize(caller, auth::Action::kManage, fleet_id);
  if (valid.ok()) valid = core::ValidateId("alias", alias);
  if (valid.ok()) valid = core::ValidateId("fleet_id", fleet_id);
  if (!valid.ok()) return valid;
  if (alias == fleet_id) {
    return absl::InvalidArgumentError(
        absl::StrCat("alias \"", alias, "\" cannot name itself"));
  }
  if (std::optional<std::string> target = memory.aliases().Resolve(fleet_id)) {
    return absl::InvalidArgumentError(
        absl::StrCat("fleet_id: \"", fleet_id, "\" is an alias (of fleet \"",
                     *target, "\"); an alias names a fleet"));
  }
  absl::StatusOr<std::vector<std::pair<std::string, std::string>>> fleets =
      memory.Fleets();
  if (!fleets.ok()) return fleets.status();
  bool found = false;
  for (const auto& [id, replica] : *fleets) {
    if (id == alias) {
      return absl::AlreadyExistsError(absl::StrCat(
          "alias: \"", alias, "\" is a fleet's id; an alias needs its own"));
    }
    found |= id == fleet_id;
  }
  if (!found) {
    return absl::NotFoundError(
        absl::StrCat("fleet \"", fleet_id, "\" does not exist"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status MemoryApi::CreateAlias(const auth::Principal& caller,
                                    const v1::CreateAliasRequest& request,
                                    v1::CreateAliasResponse* response) {
  absl::Status valid =
      CheckAliasTarget(caller, *memory_, request.alias(), request.fleet_id());
  if (!valid.ok()) return valid;
  valid = memory_->aliases().Create(request.alias(), request.fleet_id());
  if (!valid.ok()) return valid;
  response->mutable_alias()->set_alias(request.alias());
  response->mutable_alias()->set_fleet_id(request.fleet_id());
  return absl::OkStatus();
}

absl::Status MemoryApi::SwitchAlias(const auth::Principal& caller,
                                    const v1::SwitchAliasRequest& request,
                                    v1::SwitchAliasResponse* response) {
  absl::Status valid =
      CheckAliasTarget(caller, *memory_, request.alias(), request.fleet_id());
  if (!valid.ok()) return valid;
  absl::StatusOr<std::string> before =
      memory_->aliases().Switch(request.alias(), request.fleet_id());
  if (!before.ok()) return before.status();
  response->mutable_alias()->set_alias(request.alias());
  response->mutable_alias()->set_fleet_id(request.fleet_id());
  response->set_previous_fleet_id(*before);
  return absl::OkStatus();
}

absl::Status MemoryApi::DeleteAlias(const auth::Principal& caller,
                                    const v1::DeleteAliasRequest& request,
                                    v1::DeleteAliasResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kManage, request.alias());
  if (!allowed.ok()) return allowed;
  if (absl::Status valid = core::ValidateId("alias", request.alias());
      !valid.ok()) {
    return valid;
  }
  absl::StatusOr<std::string> before =
      memory_->aliases().Delete(request.alias());
  if (!before.ok()) return before.status();
  response->set_previous_fleet_id(*before);
  return absl::OkStatus();
}

absl::Status MemoryApi::ListAliases(const auth::Principal& caller,
                                    const v1::ListAliasesRequest& request,
                                    v1::ListAliasesResponse* response) {
  absl::StatusOr<std::vector<engine::FleetAlias>> aliases =
      memory_->aliases().List();
  if (!aliases.ok()) return aliases.status();
  for (const engine::FleetAlias& alias : *aliases) {
    if (!auth::MaySeeFleet(caller, alias.alias) &&
        !auth::MaySeeFleet(caller, alias.fleet_id)) {
      continue;
    }
    v1::FleetAlias* out = response->add_aliases();
    out->set_alias(alias.alias);
    out->set_fleet_id(alias.fleet_id);
  }
  return absl::OkStatus();
}

}  // namespace fleetmem::transport
