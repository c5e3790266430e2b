#include "services/transport/memory_api.h"

#include <algorithm>
#include <filesystem>
#include <map>
#include <memory>
#include <optional>
#include <set>
#include <system_error>
#include <utility>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "services/core/validation.h"
#include "services/transport/proto_convert.h"
#include "services/transport/upload_checks.h"

namespace fleetmem::transport {
namespace {

namespace fs = std::filesystem;
using google::protobuf::Message;

// Adapts a typed member to the generic form. The gateway makes its messages
// from the method's descriptor with the generated factory, so the down-casts
// hold.
template <typename Request, typename Response>
std::function<absl::Status(MemoryApi*, const auth::Principal&, const Message&,
                           Message*)>
Typed(absl::Status (MemoryApi::*member)(const auth::Principal&, const Request&,
                                        Response*)) {
  return [member](MemoryApi* api, const auth::Principal& caller,
                  const Message& request, Message* response) {
    return (api->*member)(caller, static_cast<const Request&>(request),
                          static_cast<Response*>(response));
  };
}

// 1-64 characters of [A-Za-z0-9._-], not "." or "..".
absl::Status ValidateSnapshotName(absl::string_view name) {
  const bool valid_chars =
      !name.empty() && name.size() <= 64 &&
      std::all_of(name.begin(), name.end(), [](char c) {
        return absl::ascii_isalnum(static_cast<unsigned char>(c)) || c == '.' ||
               c == '_' || c == '-';
      });
  if (!valid_chars || name == "." || name == "..") {
    return absl::InvalidArgumentError(absl::StrCat(
        "name: \"", name,
        "\" is not 1-64 characters of [A-Za-z0-9._-] (nor . or ..)"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<core::TraceKey> ParsePageToken(absl::string_view token) {
  const size_t slash = token.rfind('/');
  core::TraceKey key;
  if (slash == absl::string_view::npos ||
      !absl::SimpleAtoi(token.substr(slash + 1), &key.seq) ||
      !core::ValidateId("robot_id", std::string(token.substr(0, slash))).ok()) {
    return absl::InvalidArgumentError(
        "page_token: malformed (pass next_page_token of the previous answer)");
  }
  key.robot_id = std::string(token.substr(0, slash));
  return key;
}

std::string MakePageToken(const core::TraceKey& key) {
  return absl::StrCat(key.robot_id, "/", key.seq);
}

MemoryApi::MemoryApi(engine::MemoryEngine* engine, FleetMemory* memory,
                     ApiOptions options)
    : engine_(engine), memory_(memory), options_(std::move(options)) {
  methods_["Consolidate"] = Typed(&MemoryApi::Consolidate);
  methods_["SampleReplay"] = Typed(&MemoryApi::SampleReplay);
  methods_["QueryPlace"] = Typed(&MemoryApi::QueryPlace);
  methods_["GetStats"] = Typed(&MemoryApi::GetStats);
  methods_["ListFleets"] = Typed(&MemoryApi::ListFleets);
  methods_["ListClusters"] = Typed(&MemoryApi::ListClusters);
  methods_["ListEvents"] = Typed(&MemoryApi::ListEvents);
  methods_["ListTraces"] = Typed(&MemoryApi::ListTraces);
  methods_["CreateSnapshot"] = Typed(&MemoryApi::CreateSnapshot);
  methods_["UploadTraces"] = Typed(&MemoryApi::UploadTraces);
}

bool MemoryApi::Serves(absl::string_view method_name) const {
  return methods_.contains(method_name) || method_name == "WatchMemory";
}

absl::Status MemoryApi::Call(absl::string_view method_name,
                             const auth::Principal& caller,
                             const Message& request, Message* response,
                             const CallOptions& how) {
  auto it = methods_.find(method_name);
  if (it == methods_.end()) {
    return absl::UnimplementedError(
        absl::StrCat("method ", method_name, " is not served here"));
  }
  if (method_name == "ListFleets") {
    return ListAllFleets(caller, static_cast<v1::ListFleetsResponse*>(response),
                         how);
  }
  if (method_name == "UploadTraces") {  // FleetMemory routes uploads itself
    return Upload(caller, static_cast<const v1::UploadTracesRequest&>(request),
                  static_cast<v1::UploadTracesResponse*>(response), how);
  }
  absl::Status status;
  if (RouteToOwner(method_name, caller, request, response, how, &status)) {
    return status;
  }
  return it->second(this, caller, request, response);
}

bool MemoryApi::RouteToOwner(absl::string_view method_name,
                             const auth::Principal& caller,
                             const Message& request, Message* response,
                             const CallOptions& how, absl::Status* status) {
  // Every fleet's request names it in `fleet_id`; CreateSnapshot names
  // none and is this replica's own.
  const google::protobuf::FieldDescriptor* field =
      request.GetDescriptor()->FindFieldByName("fleet_id");
  if (field == nullptr) return false;
  const std::string fleet_id =
      request.GetReflection()->GetString(request, field);
  // The edge's check of the fleet id, for every fleet's call in both
  // modes (uploads: upload_checks.h); trusted inside from here.
  *status = core::ValidateId("fleet_id", fleet_id);
  if (!status->ok()) return true;
  // Authorised here: the owner serves the forwarded call as this replica's
  // (an admin of the cluster's credentials).
  auth::Action action = auth::Action::kStats;
  std::string robot_id;
  if (method_name == "Consolidate") {
    action = auth::Action::kConsolidate;
  } else if (method_name == "SampleReplay") {
    action = auth::Action::kSample;
    robot_id = static_cast<const v1::SampleReplayRequest&>(request).robot_id();
  } else if (method_name == "QueryPlace") {
    action = auth::Action::kQuery;
  }
  *status = auth::Authorize(caller, action, fleet_id, robot_id);
  if (!status->ok()) return true;
  absl::StatusOr<std::optional<std::string>> owner = memory_->Owner(fleet_id);
  if (!owner.ok()) {
    *status = owner.status();
    return true;
  }
  if (!owner->has_value()) return false;
  if (how.forwarded) {
    *status = absl::UnavailableError(absl::StrCat(
        "fleet \"", fleet_id, "\" is owned by replica \"", **owner,
        "\", not by \"", memory_->self(), "\" (ownership moved); retry"));
    return true;
  }
  *status = memory_->Forward(
      **owner, std::string_view(method_name.data(), method_name.size()),
      request, response, how.deadline);
  return true;
}

absl::Status MemoryApi::ListAllFleets(const auth::Principal& caller,
                                      v1::ListFleetsResponse* response,
                                      const CallOptions& how) {
  absl::StatusOr<std::vector<std::pair<std::string, std::string>>> fleets =
      memory_->Fleets();
  if (!fleets.ok()) return fleets.status();
  const std::string& self = memory_->self();
  std::map<std::string, v1::FleetSummary> summaries;
  std::set<std::string> owners;
  for (const auto& [fleet_id, owner] : *fleets) {
    if (!auth::MaySeeFleet(caller, fleet_id)) continue;
    // A forwarded ListFleets answers for this replica's fleets only.
    if (how.forwarded && owner != self) continue;
    v1::FleetSummary& summary = summaries[fleet_id];
    summary.set_fleet_id(fleet_id);
    if (owner == self) {
      absl::StatusOr<engine::FleetStats> stats = engine_->GetStats(fleet_id);
      if (stats.ok()) FleetSummaryToProto(fleet_id, *stats, &summary);
    }
    summary.set_replica(owner);
    if (owner != self && !owner.empty()) owners.insert(owner);
  }
  if (!how.forwarded && !owners.empty()) {
    AddOwnersCounts({owners.begin(), owners.end()}, how.deadline, &summaries);
  }
  for (auto& [fleet_id, summary] : summaries) {
    *response->add_fleets() = std::move(summary);
  }
  return absl::OkStatus();
}

void MemoryApi::AddOwnersCounts(
    const std::vector<std::string>& owners, absl::Time deadline,
    std::map<std::string, v1::FleetSummary>* summaries) {
  const absl::Time now = absl::Now();
  const absl::Time by =
      std::min(now + options_.list_peers_timeout,
               deadline == absl::InfiniteFuture() ? deadline
                                                  : now + (deadline - now) / 2);
  std::vector<v1::ListFleetsResponse> theirs(owners.size());
  std::vector<google::protobuf::Message*> answers;
  for (v1::ListFleetsResponse& one : theirs) answers.push_back(&one);
  const std::vector<absl::Status> asked = memory_->ForwardEach(
      owners, "ListFleets", v1::ListFleetsRequest(), answers, by);
  for (size_t i = 0; i < owners.size(); ++i) {
    if (!asked[i].ok()) continue;  // their fleets listed by id alone
    for (const v1::FleetSummary& summary : theirs[i].fleets()) {
      auto it = summaries->find(summary.fleet_id());
      if (it != summaries->end() && summary.replica() == owners[i]) {
        it->second = summary;
      }
    }
  }
}

absl::Status MemoryApi::Consolidate(const auth::Principal& caller,
                                    const v1::ConsolidateRequest& request,
                                    v1::ConsolidateResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kConsolidate, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<engine::ConsolidateResult> result =
      memory_->Consolidate(request.fleet_id());
  if (!result.ok()) return result.status();
  ConsolidateResultToProto(*result, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::SampleReplay(const auth::Principal& caller,
                                     const v1::SampleReplayRequest& request,
                                     v1::SampleReplayResponse* response) {
  absl::Status allowed = auth::Authorize(
      caller, auth::Action::kSample, request.fleet_id(), request.robot_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<std::vector<core::MemoryTrace>> traces =
      memory_->SampleReplay(request.fleet_id(), request.robot_id(),
                            request.count(), request.request_id());
  if (!traces.ok()) return traces.status();
  SampledTracesToProto(*traces, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::QueryPlace(const auth::Principal& caller,
                                   const v1::QueryPlaceRequest& request,
                                   v1::QueryPlaceResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kQuery, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<std::vector<engine::PlaceMatch>> matches =
      engine_->QueryPlace(request.fleet_id(), QueryFromProto(request));
  if (!matches.ok()) return matches.status();
  MatchesToProto(*matches, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::GetStats(const auth::Principal& caller,
                                 const v1::GetStatsRequest& request,
                                 v1::GetStatsResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kStats, request.fleet_id());
  if (!allowed.ok()) return allowed;
  const engine::Backlog backlog = memory_->Backlog(request.fleet_id());
  absl::StatusOr<engine::FleetStats> stats =
      engine_->GetStats(request.fleet_id());
  // A fleet whose first uploads are acknowledged but not applied yet exists
  // in its log only: its stats are its backlog.
  if (absl::IsNotFound(stats.status()) && backlog.traces > 0) {
    stats = engine::FleetStats{};
  }
  if (!stats.ok()) return stats.status();
  StatsToProto(*stats, response);
  BacklogToProto(backlog, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::ListFleets(const auth::Principal& caller,
                                   const v1::ListFleetsRequest& request,
                                   v1::ListFleetsResponse* response) {
  return ListAllFleets(caller, response, CallOptions());
}

absl::Status MemoryApi::ListClusters(const auth::Principal& caller,
                                     const v1::ListClustersRequest& request,
                                     v1::ListClustersResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kStats, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<engine::ClusterListing> listing =
      engine_->ListClusters(request.fleet_id(), request.include_places());
  if (!listing.ok()) return listing.status();
  ClustersToProto(*listing, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::UploadTraces(const auth::Principal& caller,
                                     const v1::UploadTracesRequest& request,
                                     v1::UploadTracesResponse* response) {
  return Upload(caller, request, response, CallOptions());
}

absl::Status MemoryApi::Upload(const auth::Principal& caller,
                               const v1::UploadTracesRequest& request,
                               v1::UploadTracesResponse* response,
                               const CallOptions& how) {
  absl::StatusOr<CheckedUpload> checked = CheckUpload(caller, request);
  if (!checked.ok()) return checked.status();
  UploadOptions options;
  options.wait_applied = checked->wait_applied;
  options.forwarded = how.forwarded;
  options.deadline = how.deadline;
  absl::StatusOr<Uploaded> uploaded =
      memory_->Upload(request.fleet_id(), checked->traces, options);
  if (!uploaded.ok()) return uploaded.status();
  AddUploadResult(uploaded->result, response);
  response->set_last_sequence(uploaded->sequence);
  response->set_applied(uploaded->applied);
  if (options_.on_upload_bytes) {
    options_.on_upload_bytes(request.fleet_id(), request.ByteSizeLong());
  }
  return absl::OkStatus();
}

absl::Status MemoryApi::CheckWatch(const auth::Principal& caller,
                                   const v1::WatchMemoryRequest& request) {
  const std::string& fleet_id = request.fleet_id();
  if (absl::Status id = core::ValidateId("fleet_id", fleet_id); !id.ok()) {
    return id;
  }
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kWatch, fleet_id);
  if (!allowed.ok()) return allowed;
  absl::StatusOr<std::optional<std::string>> owner = memory_->Owner(fleet_id);
  if (!owner.ok()) return owner.status();
  if (owner->has_value()) {
    return absl::UnavailableError(absl::StrCat("fleet \"", fleet_id,
                                               "\" is served by replica \"",
                                               **owner, "\": watch it there"));
  }
  return absl::OkStatus();
}

absl::Status MemoryApi::Watch(
    const auth::Principal& caller, const v1::WatchMemoryRequest& request,
    absl::Time until, absl::Duration heartbeat, const std::atomic<bool>* stop,
    const std::function<bool(const v1::MemoryEvent*)>& on_event) {
  if (absl::Status allowed = CheckWatch(caller, request); !allowed.ok()) {
    return allowed;
  }
  const std::string& fleet_id = request.fleet_id();
  // Subscribed before the first read, so that no event falls between them
  // (as WatchReactor).
  struct Wakeup {
    absl::Mutex mu;
    uint64_t newest ABSL_GUARDED_BY(mu) = 0;
  };
  auto wakeup = std::make_shared<Wakeup>();
  const uint64_t subscription =
      engine_->Subscribe(fleet_id, [wakeup](uint64_t last_event_id) {
        absl::MutexLock lock(&wakeup->mu);
        wakeup->newest = std::max(wakeup->newest, last_event_id);
      });
  uint64_t cursor = request.after_event();
  absl::Status ended = absl::OkStatus();
  auto stopped = [&] {
    return (stop != nullptr && stop->load()) || absl::Now() >= until;
  };
  while (!stopped()) {
    absl::StatusOr<std::vector<core::MemoryEvent>> events =
        engine_->ReadEvents(fleet_id, cursor);
    if (!events.ok()) {  // a fleet that does not exist yet reads empty
      ended = events.status();
      break;
    }
    bool open = true;
    for (const core::MemoryEvent& event : *events) {
      v1::MemoryEvent proto;
      EventToProto(event, &proto);
      cursor = event.id;
      if (!(open = on_event(&proto))) break;
    }
    if (!open) break;
    if (!events->empty()) continue;  // read again until none are left
    // Caught up: wait for a newer event, the end, or the next heartbeat.
    const absl::Time beat = std::min(until, absl::Now() + heartbeat);
    bool woken = false;
    while (!woken && !stopped() && absl::Now() < beat) {
      absl::MutexLock lock(&wakeup->mu);
      auto newer = [&wakeup, cursor]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(
                       wakeup->mu) { return wakeup->newest > cursor; };
      // In slices, so that `stop` is seen within a quarter second.
      woken = wakeup->mu.AwaitWithDeadline(
          absl::Condition(&newer),
          std::min(beat, absl::Now() + absl::Milliseconds(250)));
    }
    if (!woken && !stopped() && !on_event(nullptr)) break;
  }
  engine_->Unsubscribe(subscription);
  return ended;
}

absl::Status MemoryApi::ListEvents(const auth::Principal& caller,
                                   const v1::ListEventsRequest& request,
                                   v1::ListEventsResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kStats, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<std::vector<core::MemoryEvent>> events =
      engine_->ReadEvents(request.fleet_id(), request.after());
  if (!events.ok()) return events.status();
  if (events->empty()) {
    // The engine reads no events of a fleet it does not know (a watch may
    // wait for its creation); this call says NOT_FOUND instead.
    absl::Status exists = engine_->CheckFleetExists(request.fleet_id());
    if (!exists.ok()) return exists;
    response->set_last_event_id(request.after());
    return absl::OkStatus();
  }
  for (const core::MemoryEvent& event : *events) {
    EventToProto(event, response->add_events());
  }
  response->set_last_event_id(events->back().id);
  return absl::OkStatus();
}

absl::Status MemoryApi::ListTraces(const auth::Principal& caller,
                                   const v1::ListTracesRequest& request,
                                   v1::ListTracesResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kStats, request.fleet_id());
  if (!allowed.ok()) return allowed;
  size_t page_size = request.page_size();
  if (page_size == 0) page_size = options_.default_page_size;
  if (page_size > options_.max_page_size) {
    return absl::InvalidArgumentError(absl::StrCat("page_size: ", page_size,
                                                   " is over the limit of ",
                                                   options_.max_page_size));
  }
  std::optional<core::TraceKey> after;
  if (!request.page_token().empty()) {
    absl::StatusOr<core::TraceKey> key = ParsePageToken(request.page_token());
    if (!key.ok()) return key.status();
    after = std::move(*key);
  }
  absl::StatusOr<engine::TracePage> page =
      engine_->ListTraces(request.fleet_id(), after, page_size);
  if (!page.ok()) return page.status();
  for (const core::MemoryTrace& trace : page->traces) {
    TraceToProto(trace, response->add_traces());
  }
  if (page->more) {
    response->set_next_page_token(MakePageToken(page->traces.back().key()));
  }
  response->set_total_traces(page->total);
  return absl::OkStatus();
}

absl::Status MemoryApi::CreateSnapshot(const auth::Principal& caller,
                                       const v1::CreateSnapshotRequest& request,
                                       v1::CreateSnapshotResponse* response) {
  absl::Status allowed = auth::Authorize(caller, auth::Action::kSnapshot, {});
  if (!allowed.ok()) return allowed;
  absl::Status valid = ValidateSnapshotName(request.name());
  if (!valid.ok()) return valid;
  if (options_.snapshot_root.empty()) {
    return absl::FailedPreconditionError(
        "snapshots are off on this server (no snapshot directory)");
  }
  const fs::path path = fs::path(options_.snapshot_root) / request.name();
  std::error_code error;
  fs::create_directories(options_.snapshot_root, error);
  if (error) {
    return absl::InternalError(absl::StrCat(
        "snapshot directory ", options_.snapshot_root,
        " cannot be created: ", error.message(), "; no snapshot was taken"));
  }
  // create_directory is the claim on the name: false if it exists.
  if (!fs::create_directory(path, error)) {
    if (error) {
      return absl::InternalError(absl::StrCat(
          "snapshot ", path.string(), " cannot be created: ", error.message(),
          "; no snapshot was taken"));
    }
    return absl::AlreadyExistsError(absl::StrCat(
        "snapshot ", path.string(), " exists; choose another name"));
  }
  const int64_t now_ns = absl::GetCurrentTimeNanos();
  absl::Status taken = engine_->Checkpoint((path / "db").string());
  if (!taken.ok()) {
    fs::remove_all(path, error);
    return absl::Status(
        taken.code(), absl::StrCat(taken.message(), "; no snapshot was taken (",
                                   path.string(), " removed)"));
  }
  response->set_path(path.string());
  response->set_fleets(static_cast<uint32_t>(engine_->ListFleets().size()));
  response->set_timestamp_ns(now_ns);
  return absl::OkStatus();
}

}  // namespace fleetmem::transport
