// The alias commands of the `fleetmem` tool, and delete-fleet (commands.h).
#include <ostream>

#include "absl/strings/str_cat.h"
#include "clients/cli/commands.h"

namespace fleetmem::cli {
namespace {

void PrintAlias(const v1::FleetAlias& alias, std::ostream& out) {
  out << alias.alias() << " -> " << alias.fleet_id() << "\n";
}

}  // namespace

int RunDeleteFleet(const Invocation& invocation) {
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<std::string> confirm = invocation.flags->Required("confirm");
  if (!confirm.ok()) return UsageError(invocation, confirm.status());
  if (*confirm != *fleet) {
    return UsageError(invocation,
                      absl::InvalidArgumentError(absl::StrCat(
                          "--confirm \"", *confirm, "\" is not --fleet \"",
                          *fleet, "\"; nothing was deleted")));
  }
  absl::StatusOr<v1::DeleteFleetResponse> deleted =
      Connect(invocation)->DeleteFleet(*fleet);
  if (!deleted.ok()) return ServerError(invocation, deleted.status());
  return PrintResponse(
      invocation, *deleted,
      [&fleet](const v1::DeleteFleetResponse& response, std::ostream& out) {
        out << "fleet " << *fleet << " deleted (" << response.traces_deleted()
            << " traces)\n";
      });
}

int RunAliases(const Invocation& invocation) {
  absl::StatusOr<v1::ListAliasesResponse> aliases =
      Connect(invocation)->ListAliases();
  if (!aliases.ok()) return ServerError(invocation, aliases.status());
  return PrintResponse(
      invocation, *aliases,
      [](const v1::ListAliasesResponse& listed, std::ostream& out) {
        if (listed.aliases().empty()) out << "no aliases\n";
        for (const v1::FleetAlias& alias : listed.aliases()) {
          PrintAlias(alias, out);
        }
      });
}

int RunCreateAlias(const Invocation& invocation) {
  absl::StatusOr<std::string> alias = invocation.flags->Required("alias");
  if (!alias.ok()) return UsageError(invocation, alias.status());
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<v1::CreateAliasResponse> made =
      Connect(invocation)->CreateAlias(*alias, *fleet);
  if (!made.ok()) return ServerError(invocation, made.status());
  return PrintResponse(
      invocation, *made,
      [](const v1::CreateAliasResponse& response, std::ostream& out) {
        PrintAlias(response.alias(), out);
      });
}

int RunSwitchAlias(const Invocation& invocation) {
  absl::StatusOr<std::string> alias = invocation.flags->Required("alias");
  if (!alias.ok()) return UsageError(invocation, alias.status());
  absl::StatusOr<std::string> fleet = invocation.flags->Required("fleet");
  if (!fleet.ok()) return UsageError(invocation, fleet.status());
  absl::StatusOr<v1::SwitchAliasResponse> switched =
      Connect(invocation)->SwitchAlias(*alias, *fleet);
  if (!switched.ok()) return ServerError(invocation, switched.status());
  return PrintResponse(
      invocation, *switched,
      [](const v1::SwitchAliasResponse& response, std::ostream& out) {
        PrintAlias(response.alias(), out);
        out << "(was " << response.previous_fleet_id() << ")\n";
      });
}

int RunDeleteAlias(const Invocation& invocation) {
  absl::StatusOr<std::string> alias = invocation.flags->Required("alias");
  if (!alias.ok()) return UsageError(invocation, alias.status());
  absl::StatusOr<v1::DeleteAliasResponse> deleted =
      Connect(invocation)->DeleteAlias(*alias);
  if (!deleted.ok()) return ServerError(invocation, deleted.status());
  return PrintResponse(
      invocation, *deleted,
      [&alias](const v1::DeleteAliasResponse& response, std::ostream& out) {
        out << "alias " << *alias << " deleted (it named "
            << response.previous_fleet_id() << ")\n";
      });
}

}  // namespace fleetmem::cli
