#include "services/auth/access_policy.h"

#include <algorithm>

#include "absl/strings/str_cat.h"

namespace fleetmem::auth {
namespace {

bool InFleet(const Principal& principal, absl::string_view fleet_id) {
  return std::any_of(principal.fleets.begin(), principal.fleets.end(),
                     [&](const std::string& fleet) {
                       return fleet == "*" || fleet == fleet_id;
                     });
}

absl::Status Denied(const Principal& principal, Action action,
                    absl::string_view why) {
  return absl::PermissionDeniedError(
      absl::StrCat(RoleName(principal.role), " \"", principal.name,
                   "\" may not ", ActionName(action), ": ", why));
}

}  // namespace

absl::string_view RoleName(Role role) {
  switch (role) {
    case Role::kRobot:
      return "robot";
    case Role::kReader:
      return "reader";
    case Role::kAdmin:
      return "admin";
  }
  return "?";
}

Principal Principal::Anonymous() {
  return Principal{"anonymous", Role::kAdmin, "", {"*"}};
}

absl::string_view ActionName(Action action) {
  switch (action) {
    case Action::kUpload:
      return "upload";
    case Action::kConsolidate:
      return "consolidate";
    case Action::kSample:
      return "sample replay";
    case Action::kQuery:
      return "query places";
    case Action::kWatch:
      return "watch events";
    case Action::kStats:
      return "read stats";
    case Action::kSnapshot:
      return "take snapshots";
    case Action::kDelete:
      return "delete traces";
    case Action::kRescore:
      return "update rewards";
    case Action::kManage:
      return "manage fleets";
  }
  return "?";
}

absl::Status Authorize(const Principal& principal, Action action,
                       absl::string_view fleet_id, absl::string_view robot_id) {
  if (principal.role == Role::kAdmin) return absl::OkStatus();
  if (action == Action::kSnapshot) {
    return Denied(principal, action, "only an admin may");
  }
  if (!InFleet(principal, fleet_id)) {
    return Denied(
        principal, action,
        absl::StrCat("it does not belong to fleet \"", fleet_id, "\""));
  }
  switch (action) {
    case Action::kQuery:
    case Action::kWatch:
    case Action::kStats:
      return absl::OkStatus();
    case Action::kConsolidate:
    case Action::kManage:
      return Denied(principal, action, "only an admin may");
    case Action::kUpload:
      if (principal.role == Role::kRobot) return absl::OkStatus();
      return Denied(principal, action, "a reader is read-only");
    case Action::kSample:
    case Action::kDelete:
    case Action::kRescore:
      if (principal.role != Role::kRobot) {
        return Denied(principal, action,
                      action == Action::kSample
                          ? "a reader is read-only (sampling changes replay "
                            "weights)"
                          : "a reader is read-only");
      }
      if (robot_id.empty()) {
        return Denied(principal, action,
                      absl::StrCat("a robot names its own robot id \"",
                                   principal.robot_id, "\" (robot_id)"));
      }
      if (robot_id != principal.robot_id) {
        return Denied(
            principal, action,
            absl::StrCat("it acts only for its own robot id \"",
                         principal.robot_id, "\", not \"", robot_id, "\""));
      }
      return absl::OkStatus();
    case Action::kSnapshot:
      break;
  }
  return Denied(principal, action, "unknown action");
}

bool MaySeeFleet(const Principal& principal, absl::string_view fleet_id) {
  return principal.role == Role::kAdmin || InFleet(principal, fleet_id);
}

absl::Status AuthorizeUploadAs(const Principal& principal,
                               absl::string_view robot_id) {
  if (principal.role == Role::kAdmin) return absl::OkStatus();
  if (principal.role == Role::kRobot && robot_id == principal.robot_id) {
    return absl::OkStatus();
  }
  return Denied(
      principal, Action::kUpload,
      absl::StrCat("a trace of robot \"", robot_id, "\" (it uploads only as \"",
                   principal.robot_id, "\")"));
}

}  // namespace fleetmem::auth
