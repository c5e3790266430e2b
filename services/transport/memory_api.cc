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
#include "absl/strings/str_join.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "services/common/files.h"
#include "services/core/absl_view.h"
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

// The code of codes_by_encoder that the fleet's encoder made.
absl::StatusOr<const v1::EncoderCode*> PickEncoderCode(
    const v1::QueryPlaceRequest& request,
    const std::optional<engine::FleetShape>& shape) {
  if (request.code_size() > 0) {
    return absl::InvalidArgumentError(
        "code and codes_by_encoder: give one of them");
  }
  std::set<std::string> named;
  for (const v1::EncoderCode& code : request.codes_by_encoder()) {
    if (!named.insert(code.encoder_version()).second) {
      return absl::InvalidArgumentError(
          absl::StrCat("codes_by_encoder: encoder \"", code.encoder_version(),
                       "\" is named twice"));
    }
  }
  if (!shape.has_value()) {
    return absl::NotFoundError(
        absl::StrCat("fleet \"", request.fleet_id(), "\" does not exist"));
  }
  for (const v1::EncoderCode& code : request.codes_by_encoder()) {
    if (code.encoder_version() == shape->encoder_version) return &code;
  }
  return absl::FailedPreconditionError(
      absl::StrCat("codes_by_encoder: none is of fleet \"", request.fleet_id(),
                   "\"'s encoder \"", shape->encoder_version,
                   "\" (given: ", absl::StrJoin(named, ", "), ")"));
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
  methods_["DeleteTraces"] = Typed(&MemoryApi::DeleteTraces);
  methods_["UpdateRewards"] = Typed(&MemoryApi::UpdateRewards);
  methods_["GetTraces"] = Typed(&MemoryApi::GetTraces);
  methods_["CreateFleet"] = Typed(&MemoryApi::CreateFleet);
  methods_["GetFleet"] = Typed(&MemoryApi::GetFleet);
  methods_["UpdateFleet"] = Typed(&MemoryApi::UpdateFleet);
  methods_["UploadTraces"] = Typed(&MemoryApi::UploadTraces);
  methods_["ImportTraces"] = Typed(&MemoryApi::ImportTraces);
  methods_["DeleteFleet"] = Typed(&MemoryApi::DeleteFleet);
  methods_["CreateAlias"] = Typed(&MemoryApi::CreateAlias);
  methods_["SwitchAlias"] = Typed(&MemoryApi::SwitchAlias);
  methods_["DeleteAlias"] = Typed(&MemoryApi::DeleteAlias);
  methods_["ListAliases"] = Typed(&MemoryApi::ListAliases);
}

MemoryApi::Resolved MemoryApi::Resolve(const auth::Principal& caller,
                                       std::string_view name) const {
  Resolved resolved{std::string(name), caller};
  std::optional<std::string> fleet_id = memory_->aliases().Resolve(name);
  if (!fleet_id.has_value()) return resolved;
  if (auth::MaySeeFleet(caller, V(name)) &&
      !auth::MaySeeFleet(caller, *fleet_id)) {
    resolved.caller.fleets.push_back(*fleet_id);
  }
  resolved.fleet_id = *std::move(fleet_id);
  return resolved;
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
  // The alias table's calls name an alias, and are served by the replica
  // called (the table is shared): never resolved, never forwarded.
  if (method_name == "CreateAlias" || method_name == "SwitchAlias" ||
      method_name == "DeleteAlias" || method_name == "ListAliases") {
    return it->second(this, caller, request, response);
  }
  // A fleet's call: its name resolved once (an alias's fleet at this
  // moment), then served as a call naming that fleet.
  const google::protobuf::FieldDescriptor* field =
      request.GetDescriptor()->FindFieldByName("fleet_id");
  std::unique_ptr<Message> resolved_request;
  const Message* call = &request;
  Resolved resolved{{}, caller};
  if (field != nullptr) {
    const std::string name = request.GetReflection()->GetString(request, field);
    resolved = Resolve(caller, name);
    if (resolved.fleet_id != name) {
      if (method_name == "CreateFleet") {
        return absl::AlreadyExistsError(
            absl::StrCat("\"", name, "\" is an alias of fleet \"",
                         resolved.fleet_id, "\"; a fleet needs another name"));
      }
      if (method_name == "DeleteFleet") {  // never through a name that moves
        return absl::InvalidArgumentError(absl::StrCat(
            "fleet_id: \"", name, "\" is an alias (of fleet \"",
            resolved.fleet_id, "\"); DeleteFleet names the fleet itself"));
      }
      resolved_request.reset(request.New());
      resolved_request->CopyFrom(request);
      resolved_request->GetReflection()->SetString(resolved_request.get(),
                                                   field, resolved.fleet_id);
      call = resolved_request.get();
    }
  }
  if (method_name == "UploadTraces") {  // FleetMemory routes uploads itself
    return Upload(resolved.caller,
                  static_cast<const v1::UploadTracesRequest&>(*call),
                  static_cast<v1::UploadTracesResponse*>(response), how);
  }
  absl::Status status;
  if (RouteToOwner(method_name, resolved.caller, *call, response, how,
                   &status)) {
    return status;
  }
  return it->second(this, resolved.caller, *call, response);
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
  *status = AuthorizeCall(method_name, caller, request, fleet_id);
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

absl::Status MemoryApi::AuthorizeCall(absl::string_view method_name,
                                      const auth::Principal& caller,
                                      const Message& request,
                                      const std::string& fleet_id) {
  if (method_name == "Consolidate") {
    return auth::Authorize(caller, auth::Action::kConsolidate, fleet_id);
  }
  if (method_name == "SampleReplay") {
    return auth::Authorize(
        caller, auth::Action::kSample, fleet_id,
        static_cast<const v1::SampleReplayRequest&>(request).robot_id());
  }
  if (method_name == "QueryPlace") {
    return auth::Authorize(caller, auth::Action::kQuery, fleet_id);
  }
  if (method_name == "CreateFleet" || method_name == "UpdateFleet" ||
      method_name == "DeleteFleet" || method_name == "ImportTraces") {
    return auth::Authorize(caller, auth::Action::kManage, fleet_id);
  }
  if (method_name == "DeleteTraces") {
    return auth::Authorize(
        caller, auth::Action::kDelete, fleet_id,
        static_cast<const v1::DeleteTracesRequest&>(request).robot_id());
  }
  if (method_name == "UpdateRewards") {
    // Every robot named: one of another robot's traces refuses the call.
    std::set<std::string> robots;
    for (const v1::RewardUpdate& update :
         static_cast<const v1::UpdateRewardsRequest&>(request).updates()) {
      robots.insert(update.robot_id());
    }
    if (robots.empty()) robots.insert(caller.robot_id);
    for (const std::string& robot_id : robots) {
      absl::Status allowed =
          auth::Authorize(caller, auth::Action::kRescore, fleet_id, robot_id);
      if (!allowed.ok()) return allowed;
    }
    return absl::OkStatus();
  }
  return auth::Authorize(caller, auth::Action::kStats, fleet_id);
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
    absl::StatusOr<engine::FleetStats> stats =
        owner == self ? engine_->GetStats(fleet_id)
                      : absl::StatusOr<engine::FleetStats>();
    // A log whose fleet was deleted (DeleteFleet: its position stays) and
    // not made again; a fleet whose first upload waits in its log is
    // listed.
    if (owner == self && absl::IsNotFound(stats.status()) &&
        engine_->LogPosition(fleet_id).value_or(0) > 0) {
      const engine::Backlog backlog = memory_->Backlog(fleet_id);
      if (backlog.traces == 0 && backlog.entries == 0) continue;
    }
    v1::FleetSummary& summary = summaries[fleet_id];
    summary.set_fleet_id(fleet_id);
    if (owner == self) {
      if (stats.ok()) FleetSummaryToProto(fleet_id, *stats, &summary);
      absl::StatusOr<engine::FleetInfo> info = engine_->GetFleet(fleet_id);
      if (info.ok()) {
        FleetSettingsToProto(*info, summary.mutable_settings());
        summary.set_own_settings(info->own_settings);
      }
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
    std::set<std::string> listed;
    for (const v1::FleetSummary& summary : theirs[i].fleets()) {
      auto it = summaries->find(summary.fleet_id());
      if (it != summaries->end() && summary.replica() == owners[i]) {
        it->second = summary;
        listed.insert(summary.fleet_id());
      }
    }
    // The owner's fleets it did not list were deleted.
    for (auto it = summaries->begin(); it != summaries->end();) {
      const bool gone =
          it->second.replica() == owners[i] && !listed.contains(it->first);
      it = gone ? summaries->erase(it) : std::next(it);
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
  const core::ReadFilter filter = api::ReadFilterFromProto(request.filter());
  absl::StatusOr<std::vector<core::MemoryTrace>> traces = memory_->SampleReplay(
      request.fleet_id(), request.robot_id(), request.count(),
      request.request_id(), filter.selects_all() ? nullptr : &filter);
  if (!traces.ok()) return traces.status();
  if (request.columnar()) {
    TraceColumnsToProto(*traces, response->mutable_columns());
  } else {
    SampledTracesToProto(*traces, response);
  }
  return absl::OkStatus();
}

absl::Status MemoryApi::QueryPlace(const auth::Principal& caller,
                                   const v1::QueryPlaceRequest& request,
                                   v1::QueryPlaceResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kQuery, request.fleet_id());
  if (!allowed.ok()) return allowed;
  const std::optional<engine::FleetShape> shape =
      engine_->Shape(request.fleet_id());
  engine::PlaceQuery query = QueryFromProto(request);
  if (request.codes_by_encoder_size() > 0) {
    absl::StatusOr<const v1::EncoderCode*> picked =
        PickEncoderCode(request, shape);
    if (!picked.ok()) return picked.status();
    query.code.assign((*picked)->code().begin(), (*picked)->code().end());
  }
  std::vector<std::vector<float>> more_codes;
  more_codes.reserve(request.more_codes_size());
  for (const v1::QueryCode& more : request.more_codes()) {
    more_codes.emplace_back(more.code().begin(), more.code().end());
  }
  absl::StatusOr<std::vector<std::vector<engine::PlaceMatch>>> answers =
      engine_->QueryPlaces(request.fleet_id(), query, more_codes);
  if (!answers.ok()) return answers.status();
  response->set_fleet_id(request.fleet_id());
  if (shape.has_value()) response->set_encoder_version(shape->encoder_version);
  MatchesToProto(answers->front(), response);
  for (size_t i = 1; i < answers->size(); ++i) {
    v1::QueryPlaceResponse more;
    MatchesToProto((*answers)[i], &more);
    response->add_more_matches()->mutable_matches()->Swap(
        more.mutable_matches());
  }
  return absl::OkStatus();
}

absl::Status MemoryApi::DeleteFleet(const auth::Principal& caller,
                                    const v1::DeleteFleetRequest& request,
                                    v1::DeleteFleetResponse* response) {
  absl::Status allowed =
      AuthorizeCall("DeleteFleet", caller, request, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<std::vector<engine::FleetAlias>> aliases =
      memory_->aliases().List();
  if (!aliases.ok()) return aliases.status();
  for (const engine::FleetAlias& alias : *aliases) {
    if (alias.fleet_id == request.fleet_id()) {
      return absl::FailedPreconditionError(absl::StrCat(
          "alias \"", alias.alias, "\" names fleet \"", request.fleet_id(),
          "\": switch it to another fleet or delete it first; nothing was "
          "deleted"));
    }
  }
  absl::StatusOr<engine::AppliedRecord> applied =
      memory_->Call(request.fleet_id(), engine::DeleteFleetRecord{});
  if (!applied.ok()) return applied.status();
  response->set_traces_deleted(applied->fleet_deleted);
  return absl::OkStatus();
}

absl::Status MemoryApi::DeleteTraces(const auth::Principal& caller,
                                     const v1::DeleteTracesRequest& request,
                                     v1::DeleteTracesResponse* response) {
  absl::Status allowed =
      AuthorizeCall("DeleteTraces", caller, request, request.fleet_id());
  if (!allowed.ok()) return allowed;
  engine::DeleteTracesRecord call{api::FilterFromProto(request)};
  // Checked before it is logged, so that a bad one changes nothing.
  allowed =
      engine::MemoryEngine::CheckDeleteTraces(request.fleet_id(), call.filter);
  if (!allowed.ok()) return allowed;
  absl::StatusOr<engine::AppliedRecord> applied =
      memory_->Call(request.fleet_id(), call);
  if (!applied.ok()) return applied.status();
  DeleteResultToProto(applied->deleted, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::UpdateRewards(const auth::Principal& caller,
                                      const v1::UpdateRewardsRequest& request,
                                      v1::UpdateRewardsResponse* response) {
  absl::Status allowed =
      AuthorizeCall("UpdateRewards", caller, request, request.fleet_id());
  if (!allowed.ok()) return allowed;
  const std::vector<core::RewardUpdate> updates =
      api::RewardUpdatesFromProto(request);
  allowed = engine_->CheckUpdateRewards(request.fleet_id(), updates);
  if (!allowed.ok()) return allowed;
  absl::StatusOr<engine::AppliedRecord> applied =
      memory_->Call(request.fleet_id(), engine::UpdateRewardsRecord{updates});
  if (!applied.ok()) return applied.status();
  RewardsResultToProto(applied->rescored, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::GetTraces(const auth::Principal& caller,
                                  const v1::GetTracesRequest& request,
                                  v1::GetTracesResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kStats, request.fleet_id());
  if (!allowed.ok()) return allowed;
  const std::vector<core::TraceKey> keys = KeysFromProto(request.keys());
  absl::StatusOr<engine::TraceLookup> lookup =
      engine_->GetTraces(request.fleet_id(), keys);
  if (!lookup.ok()) return lookup.status();
  TraceLookupToProto(*lookup, response);
  return absl::OkStatus();
}

absl::Status MemoryApi::CreateFleet(const auth::Principal& caller,
                                    const v1::CreateFleetRequest& request,
                                    v1::CreateFleetResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kManage, request.fleet_id());
  if (!allowed.ok()) return allowed;
  const engine::CreateFleetRecord create = CreateFleetFromProto(
      request.settings(), engine_->MemoryOptionsFor(request.fleet_id()));
  // Checked before it is logged, so that a bad one changes nothing.
  allowed = engine_->CheckCreateFleet(request.fleet_id(), create);
  if (!allowed.ok()) return allowed;
  allowed = memory_->CreateFleet(request.fleet_id(), create);
  if (!allowed.ok()) return allowed;
  engine::FleetInfo made;
  made.shape = {create.code_dimension, create.encoder_version};
  made.settings = create.settings;
  made.own_settings = true;
  FleetSettingsToProto(made, response->mutable_settings());
  return absl::OkStatus();
}

absl::Status MemoryApi::GetFleet(const auth::Principal& caller,
                                 const v1::GetFleetRequest& request,
                                 v1::GetFleetResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kStats, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<engine::FleetInfo> info =
      engine_->GetFleet(request.fleet_id());
  if (!info.ok()) return info.status();
  absl::StatusOr<engine::FleetStats> stats =
      engine_->GetStats(request.fleet_id());
  if (!stats.ok()) return stats.status();
  v1::FleetSummary* fleet = response->mutable_fleet();
  FleetSummaryToProto(request.fleet_id(), *stats, fleet);
  FleetSettingsToProto(*info, fleet->mutable_settings());
  fleet->set_own_settings(info->own_settings);
  fleet->set_replica(memory_->self());
  return absl::OkStatus();
}

absl::Status MemoryApi::UpdateFleet(const auth::Principal& caller,
                                    const v1::UpdateFleetRequest& request,
                                    v1::UpdateFleetResponse* response) {
  absl::Status allowed =
      auth::Authorize(caller, auth::Action::kManage, request.fleet_id());
  if (!allowed.ok()) return allowed;
  absl::StatusOr<engine::FleetInfo> current =
      engine_->GetFleet(request.fleet_id());
  if (!current.ok()) return current.status();
  absl::StatusOr<engine::FleetSettingsUpdate> update =
      FleetUpdateFromProto(request.settings(), *current);
  if (!update.ok()) return update.status();
  // The result checked here first, so that a bad one is never logged (the
  // apply checks it again against the settings of its moment).
  engine::FleetSettings after = update->AppliedTo(current->settings);
  if (absl::Status valid = core::ValidateMemoryOptions(after.memory);
      !valid.ok()) {
    return absl::InvalidArgumentError(
        absl::StrCat("settings: ", valid.message()));
  }
  absl::StatusOr<engine::AppliedRecord> applied =
      memory_->Call(request.fleet_id(), engine::UpdateFleetRecord{*update});
  if (!applied.ok()) return applied.status();
  engine::FleetInfo info = *current;
  info.settings = applied->settings;
  FleetSettingsToProto(info, response->mutable_settings());
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

absl::StatusOr<MemoryApi::Resolved> MemoryApi::CheckWatch(
    const auth::Principal& caller, const v1::WatchMemoryRequest& request) {
  if (absl::Status id = core::ValidateId("fleet_id", request.fleet_id());
      !id.ok()) {
    return id;
  }
  Resolved resolved = Resolve(caller, request.fleet_id());
  const std::string& fleet_id = resolved.fleet_id;
  absl::Status allowed =
      auth::Authorize(resolved.caller, auth::Action::kWatch, fleet_id);
  if (!allowed.ok()) return allowed;
  absl::StatusOr<std::optional<std::string>> owner = memory_->Owner(fleet_id);
  if (!owner.ok()) return owner.status();
  if (owner->has_value()) {
    return absl::UnavailableError(absl::StrCat("fleet \"", fleet_id,
                                               "\" is served by replica \"",
                                               **owner, "\": watch it there"));
  }
  return resolved;
}

absl::Status MemoryApi::Watch(
    const auth::Principal& caller, const v1::WatchMemoryRequest& request,
    absl::Time until, absl::Duration heartbeat, const std::atomic<bool>* stop,
    const std::function<bool(const v1::MemoryEvent*)>& on_event) {
  absl::StatusOr<Resolved> resolved = CheckWatch(caller, request);
  if (!resolved.ok()) return resolved.status();
  const std::string& fleet_id = resolved->fleet_id;
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
  // The mark that makes it a snapshot: a server refuses to run on it (it
  // would turn the backup into a live store) and --restore-from copies it.
  const size_t fleets = engine_->ListFleets().size();
  if (absl::Status marked = files::WriteFile(
          (path / kSnapshotMarker).string(),
          absl::StrCat(
              "fleetmem snapshot \"", request.name(), "\" of ", fleets,
              " fleet(s), taken at ",
              absl::FormatTime(absl::RFC3339_sec, absl::FromUnixNanos(now_ns),
                               absl::UTCTimeZone()),
              "\nrestore: fleetmem-server --data-dir NEW_DIR "
              "--restore-from ",
              path.string(), "\n"));
      !marked.ok()) {
    fs::remove_all(path, error);
    return absl::Status(
        marked.code(),
        absl::StrCat(marked.message(), "; no snapshot was taken (",
                     path.string(), " removed)"));
  }
  response->set_path(path.string());
  response->set_fleets(static_cast<uint32_t>(fleets));
  response->set_timestamp_ns(now_ns);
  return absl::OkStatus();
}

}  // namespace fleetmem::transport
