// The unary calls of fleetmem.v1.MemoryService as plain functions of the
// caller's principal and the request message: one code path for both
// transports. The gRPC handlers (memory_service.h) and the REST/JSON gateway
// (services/http) authenticate the caller their own way, then call here;
// every function authorises, validates, runs the engine and fills the
// response, so both transports give the same answers and the same errors.
//
// Synchronous: engine calls block on fsync, so callers run these on worker
// threads (the gRPC pool, the HTTP server's threads).
#ifndef FLEETMEM_SERVICES_TRANSPORT_MEMORY_API_H_
#define FLEETMEM_SERVICES_TRANSPORT_MEMORY_API_H_

#include <atomic>
#include <functional>
#include <map>
#include <memory>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "absl/time/time.h"
#include "fleetmem/v1/memory.pb.h"
#include "google/protobuf/message.h"
#include "services/auth/access_policy.h"
#include "services/engine/memory_engine.h"
#include "services/transport/fleet_memory.h"

namespace fleetmem::transport {

// How a unary call came: from another replica or not, and until when its
// caller waits.
struct CallOptions {
  // The call came from another replica (kForwardedHeader): it is served
  // here or refused with UNAVAILABLE, never forwarded again.
  bool forwarded = false;
  // The caller's deadline; a call this server forwards is given up by then.
  absl::Time deadline = absl::InfiniteFuture();
};

// The file that marks a directory as a snapshot (SNAPSHOT_ROOT/NAME/
// SNAPSHOT, written last, saying what it holds and how to restore it): a
// server refuses it as its data dir, and --restore-from copies it.
inline constexpr char kSnapshotMarker[] = "SNAPSHOT";

struct ApiOptions {
  // Directory CreateSnapshot writes under (each snapshot a new directory
  // SNAPSHOT_ROOT/NAME holding db/ and SNAPSHOT); empty refuses snapshots with
  // FAILED_PRECONDITION. The server sets DATA_DIR/snapshots unless
  // --snapshot-dir says otherwise.
  std::string snapshot_root;
  // ListTraces pages: the default and the most one page may ask for.
  size_t default_page_size = 1000;
  size_t max_page_size = 10000;
  // ListFleets asks the other owners for their fleets' counts, all at
  // once, for at most this long and at most half the caller's remaining
  // time; an owner that has not answered by then (lost, partitioned) has
  // its fleets listed by id and replica alone, so the listing still
  // answers within its caller's deadline.
  absl::Duration list_peers_timeout = absl::Seconds(2);
  // Called with the size of each upload message UploadTraces stored (the
  // REST route; gRPC streams report theirs through ServiceOptions); may be
  // empty.
  std::function<void(std::string_view fleet_id, size_t bytes)> on_upload_bytes;
};

// Thread-safe.
class MemoryApi {
 public:
  // `engine` and `memory` must outlive the API. `memory` is the mode
  // (fleet_memory.h): a fleet's calls are served where it says (another
  // replica's are forwarded there after authorising the caller), and
  // Consolidate and SampleReplay go through it; ListFleets gathers every
  // server's fleets.
  MemoryApi(engine::MemoryEngine* engine, FleetMemory* memory,
            ApiOptions options = {});

  absl::Status Consolidate(const auth::Principal& caller,
                           const v1::ConsolidateRequest& request,
                           v1::ConsolidateResponse* response);
  absl::Status SampleReplay(const auth::Principal& caller,
                            const v1::SampleReplayRequest& request,
                            v1::SampleReplayResponse* response);
  absl::Status QueryPlace(const auth::Principal& caller,
                          const v1::QueryPlaceRequest& request,
                          v1::QueryPlaceResponse* response);
  absl::Status GetStats(const auth::Principal& caller,
                        const v1::GetStatsRequest& request,
                        v1::GetStatsResponse* response);
  // Only the fleets `caller` may see; never NOT_FOUND.
  absl::Status ListFleets(const auth::Principal& caller,
                          const v1::ListFleetsRequest& request,
                          v1::ListFleetsResponse* response);
  absl::Status ListClusters(const auth::Principal& caller,
                            const v1::ListClustersRequest& request,
                            v1::ListClustersResponse* response);
  // NOT_FOUND for a fleet that does not exist (yet).
  absl::Status ListEvents(const auth::Principal& caller,
                          const v1::ListEventsRequest& request,
                          v1::ListEventsResponse* response);
  absl::Status ListTraces(const auth::Principal& caller,
                          const v1::ListTracesRequest& request,
                          v1::ListTracesResponse* response);
  // One message of an upload (the REST route; gRPC streams go through
  // UploadReactor): the same checks (fleet id, the caller's rights, every
  // trace's robot id) and the same FleetMemory::Upload, so the same answer
  // and errors as a one-message stream. In distributed mode the
  // FleetMemory forwards it to the fleet's owner, which admits its load
  // (engine/admission.h).
  absl::Status UploadTraces(const auth::Principal& caller,
                            const v1::UploadTracesRequest& request,
                            v1::UploadTracesResponse* response);
  // Admin. A bulk import's chunk (v1.ImportTracesRequest): its rows as
  // uploads of a segment each (at most max_traces_per_upload; FleetMemory::
  // UploadMany: the same admission, log and apply), with the fleet's
  // place index deferred (engine::MemoryEngine::DeferIndexing) for
  // kImportIdle after each call; `finish` waits until they are applied and
  // builds the graph (IndexDeferred). A fleet that holds traces, with no
  // import under way here, is refused unless `resume`.
  absl::Status ImportTraces(const auth::Principal& caller,
                            const v1::ImportTracesRequest& request,
                            v1::ImportTracesResponse* response);
  // How long an import's deferral of the graph lasts after its last call:
  // an import abandoned without `finish` gets its graph built in the
  // background then.
  static constexpr absl::Duration kImportIdle = absl::Minutes(10);
  // Rows one ImportTraces call may carry.
  static constexpr int kMaxImportRows = 100'000;
  // Admin. Logged as the fleet's first entry (FleetMemory::CreateFleet).
  absl::Status CreateFleet(const auth::Principal& caller,
                           const v1::CreateFleetRequest& request,
                           v1::CreateFleetResponse* response);
  absl::Status GetFleet(const auth::Principal& caller,
                        const v1::GetFleetRequest& request,
                        v1::GetFleetResponse* response);
  // Admin. Through the fleet's log (FleetMemory::Call).
  absl::Status UpdateFleet(const auth::Principal& caller,
                           const v1::UpdateFleetRequest& request,
                           v1::UpdateFleetResponse* response);
  // Admin. Through the fleet's log (FleetMemory::Call), after every upload
  // acknowledged before it; refused while an alias names the fleet.
  absl::Status DeleteFleet(const auth::Principal& caller,
                           const v1::DeleteFleetRequest& request,
                           v1::DeleteFleetResponse* response);
  // Through the fleet's log in both modes (FleetMemory::Call), after every
  // upload acknowledged before them; a robot names only its own traces.
  absl::Status DeleteTraces(const auth::Principal& caller,
                            const v1::DeleteTracesRequest& request,
                            v1::DeleteTracesResponse* response);
  absl::Status UpdateRewards(const auth::Principal& caller,
                             const v1::UpdateRewardsRequest& request,
                             v1::UpdateRewardsResponse* response);
  absl::Status GetTraces(const auth::Principal& caller,
                         const v1::GetTracesRequest& request,
                         v1::GetTracesResponse* response);
  // Fleet aliases (FleetMemory::aliases()): admin only, but ListAliases,
  // which lists the aliases of the fleets the caller may see. Served by
  // the replica called (the table is shared), never forwarded.
  absl::Status CreateAlias(const auth::Principal& caller,
                           const v1::CreateAliasRequest& request,
                           v1::CreateAliasResponse* response);
  absl::Status SwitchAlias(const auth::Principal& caller,
                           const v1::SwitchAliasRequest& request,
                           v1::SwitchAliasResponse* response);
  absl::Status DeleteAlias(const auth::Principal& caller,
                           const v1::DeleteAliasRequest& request,
                           v1::DeleteAliasResponse* response);
  absl::Status ListAliases(const auth::Principal& caller,
                           const v1::ListAliasesRequest& request,
                           v1::ListAliasesResponse* response);
  // Admin only. ALREADY_EXISTS if the name is taken; on any error nothing is
  // left under the name.
  absl::Status CreateSnapshot(const auth::Principal& caller,
                              const v1::CreateSnapshotRequest& request,
                              v1::CreateSnapshotResponse* response);

  // The fleet a call naming `name` reads and writes: the alias's fleet at
  // this moment, or `name` itself; and the caller's rights through it (a
  // credential of the alias acts for the fleet it names). Every fleet's
  // call resolves its name once, here (Call; the upload and watch streams
  // when they start), so a switch never splits a call.
  struct Resolved {
    std::string fleet_id;
    auth::Principal caller;
  };
  Resolved Resolve(const auth::Principal& caller, std::string_view name) const;

  // Generic form for the HTTP gateway: the unary method `method_name` (e.g.
  // "GetStats") with messages of its request and response types.
  // UNIMPLEMENTED for a method that is not unary or not known here.
  //
  // This is where a fleet's call is routed to its owner (distributed
  // mode), as `how` says (CallOptions).
  absl::Status Call(absl::string_view method_name,
                    const auth::Principal& caller,
                    const google::protobuf::Message& request,
                    google::protobuf::Message* response,
                    const CallOptions& how = {});
  // True if Call serves `method_name`, or Watch for "WatchMemory".
  bool Serves(absl::string_view method_name) const;

  // WatchMemory for the HTTP gateway, on the calling thread: authorises
  // (auth::Action::kWatch), then hands `on_event` the fleet's events after
  // request.after_event, then live ones, until `on_event` returns false,
  // `until` passes or `*stop` becomes true. While no event comes it calls
  // `on_event(nullptr)` every `heartbeat` (the caller's chance to find a
  // closed connection). A fleet that does not exist yet is watched for its
  // first events. OK when it ended so; INVALID_ARGUMENT, OUT_OF_RANGE (the
  // cursor's events are erased; also later, if retention overtakes a slow
  // reader), UNAVAILABLE (another replica owns the fleet: watch it there),
  // the access policy's errors and a failed read.
  // Watch's checks alone (before a transport commits to a stream), after
  // resolving its name once (a watch stays on the fleet it started on: its
  // event ids are that fleet's): the fleet watched and the caller's rights.
  absl::StatusOr<Resolved> CheckWatch(const auth::Principal& caller,
                                      const v1::WatchMemoryRequest& request);
  absl::Status Watch(
      const auth::Principal& caller, const v1::WatchMemoryRequest& request,
      absl::Time until, absl::Duration heartbeat, const std::atomic<bool>* stop,
      const std::function<bool(const v1::MemoryEvent*)>& on_event);

 private:
  // The caller's right to `method_name` on `fleet_id` (a fleet's call, as
  // RouteToOwner and the typed members ask it).
  static absl::Status AuthorizeCall(absl::string_view method_name,
                                    const auth::Principal& caller,
                                    const google::protobuf::Message& request,
                                    const std::string& fleet_id);
  using Generic = std::function<absl::Status(MemoryApi*, const auth::Principal&,
                                             const google::protobuf::Message&,
                                             google::protobuf::Message*)>;

  // Forwards a fleet's call to its owner (true, with the call's status in
  // *status) or leaves it to this server (false; always, embedded).
  bool RouteToOwner(absl::string_view method_name,
                    const auth::Principal& caller,
                    const google::protobuf::Message& request,
                    google::protobuf::Message* response, const CallOptions& how,
                    absl::Status* status);
  // ListFleets: this server's fleets and every other owner's (a forwarded
  // call: this server's only).
  absl::Status ListAllFleets(const auth::Principal& caller,
                             v1::ListFleetsResponse* response,
                             const CallOptions& how);
  // Fills the summaries of the fleets `owners` own with their counts,
  // asking them all at once (ApiOptions::list_peers_timeout).
  void AddOwnersCounts(const std::vector<std::string>& owners,
                       absl::Time deadline,
                       std::map<std::string, v1::FleetSummary>* summaries);

  // ImportTraces' steps (memory_api_import.cc): OK if the fleet holds no
  // trace (nor backlog) or an import into it is under way here,
  // FAILED_PRECONDITION otherwise; the messages through UploadMany, their
  // counts added to `response` (*sent: rows of the call stored so far), the
  // error naming the rows; the last call's graph build and counts.
  absl::Status CheckNothingHeld(const std::string& fleet_id);
  absl::Status UploadImported(
      const std::string& fleet_id,
      std::span<const std::span<const core::MemoryTrace>> messages,
      const UploadOptions& options, size_t* sent,
      v1::ImportTracesResponse* response);
  absl::Status BuildImportedGraph(const std::string& fleet_id,
                                  v1::ImportTracesResponse* response);

  // UploadTraces, forwarded by another replica or not.
  absl::Status Upload(const auth::Principal& caller,
                      const v1::UploadTracesRequest& request,
                      v1::UploadTracesResponse* response,
                      const CallOptions& how);

  engine::MemoryEngine* const engine_;
  FleetMemory* const memory_;
  const ApiOptions options_;
  absl::flat_hash_map<std::string, Generic> methods_;
};

// The (robot_id, seq) cursor of a ListTraces page token; INVALID_ARGUMENT
// naming page_token when it is malformed.
absl::StatusOr<core::TraceKey> ParsePageToken(absl::string_view token);
std::string MakePageToken(const core::TraceKey& key);

}  // namespace fleetmem::transport

#endif  // FLEETMEM_SERVICES_TRANSPORT_MEMORY_API_H_
