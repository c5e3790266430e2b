// Who may do what: the one access policy of fleetmem-server. Every transport
// (gRPC now, HTTP later) authenticates a caller to a Principal (see
// authenticator.h) and asks Authorize before doing the work. Pure: no I/O.
#ifndef FLEETMEM_SERVICES_AUTH_ACCESS_POLICY_H_
#define FLEETMEM_SERVICES_AUTH_ACCESS_POLICY_H_

#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"

namespace fleetmem::auth {

enum class Role { kRobot, kReader, kAdmin };

absl::string_view RoleName(Role role);

// An authenticated caller.
struct Principal {
  // Name in the credentials file ("anonymous" when auth is off).
  std::string name;
  Role role = Role::kReader;
  // For kRobot: the robot id it acts as.
  std::string robot_id;
  // Fleets it may use; "*" is every fleet. Ignored for kAdmin.
  std::vector<std::string> fleets;

  // The caller of a server without auth: an admin of every fleet.
  static Principal Anonymous();
};

// What a call does to a fleet.
enum class Action {
  kUpload,       // UploadTraces; check each trace with AuthorizeUploadAs
  kConsolidate,  // Consolidate
  kSample,       // SampleReplay (changes replay weights)
  kQuery,        // QueryPlace
  kWatch,        // WatchMemory
  kStats,        // GetStats, ListClusters, ListEvents, ListTraces, GetTraces
  kDelete,       // DeleteTraces (of `robot_id`'s traces for a robot)
  kRescore,      // UpdateRewards (of `robot_id`'s traces for a robot)
  kManage,       // CreateFleet, UpdateFleet (an admin's only)
  kSnapshot,     // CreateSnapshot (the whole store; no fleet)
};

absl::string_view ActionName(Action action);

// OK if `principal` may do `action` on `fleet_id`; for kSample, `robot_id`
// is the robot the sample is for. PERMISSION_DENIED naming the principal,
// the action and the reason otherwise:
//   admin   everything;
//   robot   upload, sample, delete and rescore (for its own robot id:
//           `robot_id`), query, watch, stats in its fleets;
//   reader  query, watch, stats in its fleets.
// kSnapshot is an admin's only (`fleet_id` is ignored). kDelete and
// kRescore are asked once per robot whose traces the call names (a delete
// of no robot's: `robot_id` empty, an admin's only).
absl::Status Authorize(const Principal& principal, Action action,
                       absl::string_view fleet_id,
                       absl::string_view robot_id = {});

// True if `principal` may see `fleet_id` at all (ListFleets shows only
// these): an admin every fleet, others the fleets of their entry.
bool MaySeeFleet(const Principal& principal, absl::string_view fleet_id);

// OK if `principal` may upload a trace of `robot_id` (a robot only its own,
// an admin any); PERMISSION_DENIED otherwise. Call after Authorize(kUpload).
absl::Status AuthorizeUploadAs(const Principal& principal,
                               absl::string_view robot_id);

}  // namespace fleetmem::auth

#endif  // FLEETMEM_SERVICES_AUTH_ACCESS_POLICY_H_
