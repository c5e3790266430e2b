#include "services/cluster/nats_fleet_log.h"

#include <xxhash.h>

#include <algorithm>
#include <climits>
#include <memory>
#include <optional>
#include <utility>
#include <variant>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/container/flat_hash_set.h"
#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/clock.h"
#include "nats/nats.h"
#include "proto/convert/trace_convert.h"
#include "services/cluster/log_record.pb.h"
#include "services/cluster/nats_aliases.h"
#include "services/cluster/nats_status.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/storage/record_codec.h"

namespace fleetmem::cluster {
namespace {

int64_t Nanoseconds(absl::Duration d) { return absl::ToInt64Nanoseconds(d); }
int64_t Milliseconds(absl::Duration d) { return absl::ToInt64Milliseconds(d); }

std::string SnapshotSubject(std::string_view fleet_id) {
  return absl::StrCat("fleetmem.snap.", Hash(fleet_id));
}

}  // namespace

std::string FleetStreamName(std::string_view fleet_id) {
  return absl::StrCat("FLEETMEM_", Hash(fleet_id));
}
std::string FleetSubject(std::string_view fleet_id) {
  return absl::StrCat("fleetmem.log.", Hash(fleet_id));
}
std::string FleetLeaseKey(std::string_view fleet_id) {
  return absl::StrCat("fleet.", Hash(fleet_id));
}
std::string SnapshotStreamName(std::string_view fleet_id) {
  return absl::StrCat("FLEETMEM_SNAP_", Hash(fleet_id));
}

absl::Status ValidateNatsOptions(const NatsOptions& options) {
  if (options.servers.empty()) {
    return absl::InvalidArgumentError("cluster: no NATS server given");
  }
  for (const std::string& server : options.servers) {
    if (server.find(',') != std::string::npos ||
        !(absl::StartsWith(server, "nats://") ||
          absl::StartsWith(server, "tls://"))) {
      return absl::InvalidArgumentError(
          absl::StrCat("cluster: bad NATS server URL '", server, "'"));
    }
  }
  if (options.replicas < 1 || options.replicas > 5) {
    return absl::InvalidArgumentError(
        "cluster: replicas must be 1 to 5 (JetStream's limit)");
  }
  if (options.cert_file.empty() != options.key_file.empty()) {
    return absl::InvalidArgumentError(
        "cluster: a client certificate needs both its file and its key");
  }
  if (!options.cert_file.empty() && options.ca_file.empty()) {
    return absl::InvalidArgumentError(
        "cluster: a client certificate needs the CA file (TLS)");
  }
  if (options.duplicate_window < absl::Seconds(1) ||
      options.lease_ttl < absl::Seconds(1) ||
      options.timeout < absl::Milliseconds(10)) {
    return absl::InvalidArgumentError(
        "cluster: duplicate window and lease TTL must be at least 1 s, the "
        "timeout at least 10 ms");
  }
  if (options.alias_bucket.empty() ||
      options.alias_bucket.find_first_not_of(
          "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-") !=
          std::string::npos) {
    return absl::InvalidArgumentError(
        absl::StrCat("cluster: bad alias bucket name '", options.alias_bucket,
                     "' (letters, digits, _ and - only)"));
  }
  if (options.lease_bucket.empty() ||
      options.lease_bucket.find_first_not_of(
          "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789-_") !=
          std::string::npos) {
    return absl::InvalidArgumentError(
        "cluster: the lease bucket's name may hold letters, digits, - and _");
  }
  return absl::OkStatus();
}

namespace {

// Entries in flight (NatsFleetLog::Append publishes several without
// waiting for each acknowledgement): each message's slot for its outcome,
// filled in by OnAck on nats.c's thread.
struct AsyncAcks {
  struct Slot {
    std::optional<absl::StatusOr<engine::AppendedEntry>>* outcome;
    size_t* waiting;  // the append's count of outcomes not in yet
  };
  absl::Mutex mu;
  absl::CondVar acked;
  // By the message nats.c hands back to OnAck (its original).
  absl::flat_hash_map<const natsMsg*, Slot> slots ABSL_GUARDED_BY(mu);

  void Acknowledge(const natsMsg* msg,
                   absl::StatusOr<engine::AppendedEntry> outcome) {
    absl::MutexLock lock(&mu);
    auto it = slots.find(msg);
    if (it == slots.end()) return;  // no longer waited for
    *it->second.outcome = std::move(outcome);
    --*it->second.waiting;
    slots.erase(it);
    acked.SignalAll();
  }
};

// nats.c's acknowledgement handler of the asynchronous context.
void OnAck(jsCtx*, natsMsg* msg, jsPubAck* ack, jsPubAckErr* error,
           void* closure) {
  absl::StatusOr<engine::AppendedEntry> outcome = engine::AppendedEntry{};
  if (ack != nullptr) {
    outcome = engine::AppendedEntry{ack->Sequence, ack->Duplicate};
  } else {
    const natsStatus failed =
        error != nullptr && error->Err != NATS_OK ? error->Err : NATS_ERR;
    outcome =
        FromNats(failed, error != nullptr ? error->ErrCode : 0,
                 absl::StrCat("cluster: appending an entry to a fleet's log",
                              error != nullptr && error->ErrText != nullptr
                                  ? absl::StrCat(" (", error->ErrText, ")")
                                  : std::string()));
  }
  static_cast<AsyncAcks*>(closure)->Acknowledge(msg, std::move(outcome));
  natsMsg_Destroy(msg);
}

}  // namespace

struct NatsFleetLog::Handles {
  ~Handles() {
    if (async_js != nullptr) jsCtx_Destroy(async_js);
    if (kv != nullptr) kvStore_Destroy(kv);
    if (js != nullptr) jsCtx_Destroy(js);
    if (nc != nullptr) natsConnection_Destroy(nc);
  }
  natsConnection* nc = nullptr;
  jsCtx* js = nullptr;
  // Appends of several entries: published without waiting for each
  // acknowledgement (OnAck).
  jsCtx* async_js = nullptr;
  AsyncAcks acks;
  kvStore* kv = nullptr;
  absl::Mutex mu;
  absl::flat_hash_set<std::string> streams ABSL_GUARDED_BY(mu);  // by name
  // The fleet id of each log stream seen (its description).
  absl::flat_hash_map<std::string, std::string> fleet_of_log
      ABSL_GUARDED_BY(mu);
};

NatsFleetLog::NatsFleetLog(NatsOptions options,
                           std::unique_ptr<Handles> handles)
    : options_(std::move(options)), handles_(std::move(handles)) {}
NatsFleetLog::~NatsFleetLog() = default;

namespace {

using NatsOptionsPtr = std::unique_ptr<natsOptions, void (*)(natsOptions*)>;

// nats.c's options for `options`: its servers, timeouts, reconnection,
// credentials and TLS.
absl::StatusOr<NatsOptionsPtr> ConnectionOptions(const NatsOptions& options) {
  natsOptions* raw = nullptr;
  if (natsStatus s = natsOptions_Create(&raw); s != NATS_OK) {
    return FromNats(s, 0, "cluster: NATS options");
  }
  NatsOptionsPtr opts(raw, natsOptions_Destroy);
  std::vector<const char*> servers;
  for (const std::string& server : options.servers) {
    servers.push_back(server.c_str());
  }
  natsStatus s = natsOptions_SetServers(opts.get(), servers.data(),
                                        static_cast<int>(servers.size()));
  if (s == NATS_OK) {
    s = natsOptions_SetTimeout(opts.get(), Milliseconds(options.timeout));
  }
  if (s == NATS_OK) s = natsOptions_SetMaxReconnect(opts.get(), -1);
  // The next server at once when one is lost, then every 250 ms: a lease
  // is renewed every third of its time-to-live (nats.c waits 2 s by
  // default).
  if (s == NATS_OK) s = natsOptions_SetReconnectWait(opts.get(), 250);
  if (s == NATS_OK) s = natsOptions_SetReconnectJitter(opts.get(), 100, 500);
  if (s == NATS_OK) s = natsOptions_SetName(opts.get(), "fleetmem-server");
  if (s == NATS_OK && !options.credentials_file.empty()) {
    s = natsOptions_SetUserCredentialsFromFiles(
        opts.get(), options.credentials_file.c_str(), nullptr);
  }
  if (s == NATS_OK && !options.ca_file.empty()) {
    s = natsOptions_SetSecure(opts.get(), true);
    if (s == NATS_OK) {
      s = natsOptions_LoadCATrustedCertificates(opts.get(),
                                                options.ca_file.c_str());
    }
    if (s == NATS_OK && !options.cert_file.empty()) {
      s = natsOptions_LoadCertificatesChain(
          opts.get(), options.cert_file.c_str(), options.key_file.c_str());
    }
  }
  if (s != NATS_OK) return FromNats(s, 0, "cluster: NATS options");
  return opts;
}

// The lease bucket, made if missing (or found made by another replica
// meanwhile).
absl::Status OpenLeaseBucket(jsCtx* js, const NatsOptions& options,
                             kvStore** kv) {
  natsStatus s = js_KeyValue(kv, js, options.lease_bucket.c_str());
  if (s == NATS_NOT_FOUND) {
    kvConfig config;
    kvConfig_Init(&config);
    config.Bucket = options.lease_bucket.c_str();
    config.Description = "fleetmem: which replica owns each fleet";
    config.History = 1;
    config.TTL = Nanoseconds(options.lease_ttl);
    config.Replicas = options.replicas;
    config.StorageType = js_FileStorage;
    const natsStatus created = js_CreateKeyValue(kv, js, &config);
    s = created;
    if (created != NATS_OK) {
      const absl::Status not_made =
          FromNats(created, 0,
                   absl::StrCat("cluster: making the lease bucket '",
                                options.lease_bucket, "'"));
      // Made by another replica meanwhile?
      s = js_KeyValue(kv, js, options.lease_bucket.c_str());
      if (s == NATS_NOT_FOUND) {
        // Neither there nor made: a JetStream cluster that is still
        // electing its leaders, or has too few servers up for the bucket's
        // copies, refuses to make it. Worth retrying (the server's start
        // retries UNAVAILABLE until cluster.connect_timeout).
        return absl::UnavailableError(
            absl::StrCat(not_made.message(),
                         "; it is still missing, JetStream may not "
                         "be ready yet"));
      }
    }
  }
  if (s != NATS_OK) {
    return FromNats(
        s, 0,
        absl::StrCat("cluster: the lease bucket '", options.lease_bucket, "'"));
  }
  return absl::OkStatus();
}

}  // namespace

absl::StatusOr<std::unique_ptr<NatsFleetLog>> NatsFleetLog::Connect(
    NatsOptions options) {
  if (absl::Status valid = ValidateNatsOptions(options); !valid.ok()) {
    return valid;
  }
  absl::StatusOr<NatsOptionsPtr> opts = ConnectionOptions(options);
  if (!opts.ok()) return opts.status();
  auto handles = std::make_unique<Handles>();
  if (natsStatus s = natsConnection_Connect(&handles->nc, opts->get());
      s != NATS_OK) {
    return FromNats(s, 0,
                    absl::StrCat("cluster: connecting to ",
                                 absl::StrJoin(options.servers, ",")));
  }
  jsOptions js_options;
  jsOptions_Init(&js_options);
  js_options.Wait = Milliseconds(options.timeout);
  if (natsStatus s =
          natsConnection_JetStream(&handles->js, handles->nc, &js_options);
      s != NATS_OK) {
    return FromNats(s, 0, "cluster: JetStream");
  }
  js_options.PublishAsync.AckHandler = OnAck;
  js_options.PublishAsync.AckHandlerClosure = &handles->acks;
  if (natsStatus s = natsConnection_JetStream(&handles->async_js, handles->nc,
                                              &js_options);
      s != NATS_OK) {
    return FromNats(s, 0, "cluster: JetStream");
  }
  if (absl::Status bucket = OpenLeaseBucket(handles->js, options, &handles->kv);
      !bucket.ok()) {
    return bucket;
  }
  absl::StatusOr<std::unique_ptr<NatsAliases>> aliases = NatsAliases::Open(
      handles->js, options.alias_bucket, options.replicas, options.timeout);
  if (!aliases.ok()) return aliases.status();
  std::unique_ptr<NatsFleetLog> log(
      new NatsFleetLog(std::move(options), std::move(handles)));
  log->aliases_ = *std::move(aliases);
  return log;
}

engine::AliasTable& NatsFleetLog::aliases() { return *aliases_; }

absl::Status NatsFleetLog::EnsureStream(std::string_view fleet_id) {
  return EnsureFleetStream(fleet_id, FleetStreamName(fleet_id),
                           FleetSubject(fleet_id), /*is_log=*/true);
}

absl::Status NatsFleetLog::EnsureSnapshotStream(std::string_view fleet_id) {
  return EnsureFleetStream(fleet_id, SnapshotStreamName(fleet_id),
                           absl::StrCat(SnapshotSubject(fleet_id), ".*"),
                           /*is_log=*/false);
}

absl::Status NatsFleetLog::EnsureFleetStream(std::string_view fleet_id,
                                             const std::string& name,
                                             const std::string& subject_pattern,
                                             bool is_log) {
  {
    absl::MutexLock lock(&handles_->mu);
    if (handles_->streams.contains(name)) return absl::OkStatus();
  }
  const std::string description(fleet_id);
  jsStreamInfo* info = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  natsStatus s =
      js_GetStreamInfo(&info, handles_->js, name.c_str(), nullptr, &code);
  if (s == NATS_NOT_FOUND || code == JSStreamNotFoundErr) {
    jsStreamConfig config;
    jsStreamConfig_Init(&config);
    const char* subjects[] = {subject_pattern.c_str()};
    config.Name = name.c_str();
    config.Description = description.c_str();
    config.Subjects = subjects;
    config.SubjectsLen = 1;
    config.Storage = js_FileStorage;
    config.Replicas = options_.replicas;
    config.Duplicates = Nanoseconds(options_.duplicate_window);
    // A log loses no entry in its middle (Trim purges its head only).
    config.DenyDelete = is_log;
    code = static_cast<jsErrCode>(0);
    s = js_AddStream(&info, handles_->js, &config, nullptr, &code);
    // A race with another replica creating the same stream: re-read it. A
    // clustered JetStream may report the loser's create as "subjects
    // overlap" rather than "name in use"; the re-read then finds the stream
    // (or, for a stranger's stream on these subjects, NOT_FOUND).
    if (s != NATS_OK &&
        (code == JSStreamNameExistErr || code == JSStreamSubjectOverlapErr)) {
      code = static_cast<jsErrCode>(0);
      s = js_GetStreamInfo(&info, handles_->js, name.c_str(), nullptr, &code);
    }
  }
  if (s != NATS_OK) {
    return FromNats(
        s, code,
        absl::StrCat("cluster: the ", is_log ? "log" : "snapshots",
                     " of fleet \"", V(fleet_id), "\" (stream ", name, ")"));
  }
  const bool ours = info != nullptr && info->Config != nullptr &&
                    info->Config->Description != nullptr &&
                    description == info->Config->Description;
  jsStreamInfo_Destroy(info);
  if (!ours) {
    return absl::FailedPreconditionError(
        absl::StrCat("cluster: stream ", name, " is not fleet \"", V(fleet_id),
                     "\"'s (another fleet id with the same hash)"));
  }
  absl::MutexLock lock(&handles_->mu);
  handles_->streams.insert(name);
  return absl::OkStatus();
}

namespace {

// A record as JetStream's entries carry it (log_record.proto's LogRecord).
struct ToLogRecord {
  v1::LogRecord* out;
  void operator()(const engine::UploadRecord& upload) const {
    for (const core::MemoryTrace& trace : upload.traces) {
      api::TraceToProto(trace, out->mutable_upload()->add_traces());
    }
  }
  void operator()(const engine::ConsolidateRecord&) const {
    out->mutable_consolidate();
  }
  void operator()(const engine::SampleReplayRecord& call) const {
    v1::SampleReplay* sample = out->mutable_sample_replay();
    sample->set_robot_id(std::string(call.robot_id));
    sample->set_count(call.count);
    sample->set_request_id(std::string(call.request_id));
    if (call.filter != nullptr) {
      api::ReadFilterToProto(*call.filter, sample->mutable_filter());
    }
  }
  void operator()(const engine::DeleteTracesRecord& call) const {
    api::FilterToProto(call.filter, out->mutable_delete_traces());
  }
  void operator()(const engine::UpdateRewardsRecord& call) const {
    api::RewardUpdatesToProto(call.updates, out->mutable_update_rewards());
  }
  void operator()(const engine::CreateFleetRecord& call) const {
    out->set_fleet_call(storage::EncodeLoggedRecord(call));
  }
  void operator()(const engine::UpdateFleetRecord& call) const {
    out->set_fleet_call(storage::EncodeLoggedRecord(call));
  }
  void operator()(const engine::EnforceRetentionRecord& call) const {
    out->set_fleet_call(storage::EncodeLoggedRecord(call));
  }
  void operator()(const engine::DeleteFleetRecord& call) const {
    out->set_fleet_call(storage::EncodeLoggedRecord(call));
  }
};

// The record of an entry's bytes: DATA_LOSS when they do not parse,
// FAILED_PRECONDITION for a kind this version does not know (a newer one
// wrote it).
absl::StatusOr<engine::StoredRecord> DecodeRecord(std::string_view fleet_id,
                                                  uint64_t sequence,
                                                  std::string_view data) {
  v1::LogRecord record;
  if (!record.ParseFromArray(data.data(), static_cast<int>(data.size()))) {
    return absl::DataLossError(absl::StrCat("cluster: entry ", sequence,
                                            " of the log of fleet \"",
                                            V(fleet_id), "\" is malformed"));
  }
  switch (record.kind_case()) {
    case v1::LogRecord::kUpload: {
      std::vector<core::MemoryTrace> traces;
      traces.reserve(record.upload().traces_size());
      for (const ::fleetmem::v1::MemoryTrace& trace :
           record.upload().traces()) {
        traces.push_back(api::TraceFromProto(trace));
      }
      return traces;
    }
    case v1::LogRecord::kConsolidate:
      return engine::ConsolidateRecord{};
    case v1::LogRecord::kSampleReplay:
      return engine::SampleReplayCall{
          record.sample_replay().robot_id(), record.sample_replay().count(),
          record.sample_replay().request_id(),
          api::ReadFilterFromProto(record.sample_replay().filter())};
    case v1::LogRecord::kDeleteTraces:
      return engine::DeleteTracesRecord{
          api::FilterFromProto(record.delete_traces())};
    case v1::LogRecord::kUpdateRewards:
      return engine::UpdateRewardsCall{
          api::RewardUpdatesFromProto(record.update_rewards())};
    case v1::LogRecord::kFleetCall: {
      absl::StatusOr<engine::StoredRecord> call = storage::DecodeLoggedRecord(
          absl::StrCat("cluster: entry ", sequence, " of the log of fleet \"",
                       V(fleet_id), "\""),
          record.fleet_call());
      if (!call.ok()) return call.status();
      if (!std::holds_alternative<engine::CreateFleetRecord>(*call) &&
          !std::holds_alternative<engine::UpdateFleetRecord>(*call) &&
          !std::holds_alternative<engine::EnforceRetentionRecord>(*call) &&
          !std::holds_alternative<engine::DeleteFleetRecord>(*call)) {
        return absl::DataLossError(absl::StrCat(
            "cluster: entry ", sequence, " of the log of fleet \"", V(fleet_id),
            "\" carries a fleet call of another kind"));
      }
      return call;
    }
    case v1::LogRecord::KIND_NOT_SET:
      break;
  }
  return absl::FailedPreconditionError(absl::StrCat(
      "cluster: entry ", sequence, " of the log of fleet \"", V(fleet_id),
      "\" is of a kind this replica does not know (a newer version wrote "
      "it)"));
}

}  // namespace

absl::StatusOr<std::vector<engine::AppendedEntry>> NatsFleetLog::Append(
    std::string_view fleet_id, std::span<const engine::LogAppend> entries,
    const engine::AppendOptions& options) {
  if (options.above != 0) {
    return absl::InvalidArgumentError(
        "cluster: JetStream numbers a log's entries itself (no floor)");
  }
  std::vector<std::string> data;
  data.reserve(entries.size());
  for (const engine::LogAppend& entry : entries) {
    v1::LogRecord record;
    std::visit(ToLogRecord{&record}, entry.record);
    data.push_back(record.SerializeAsString());
  }
  std::vector<engine::AppendedEntry> appended;
  if (entries.size() == 1 || options.only_first) {
    // The first alone, when it must be the log's first: whether it is
    // decides whether the rest are appended.
    absl::StatusOr<engine::AppendedEntry> one =
        AppendOne(fleet_id, entries[0].id, data[0], options.only_first);
    if (!one.ok()) return one.status();
    appended.push_back(*one);
  }
  if (appended.size() == entries.size()) return appended;
  absl::StatusOr<std::vector<engine::AppendedEntry>> rest = AppendPipelined(
      fleet_id, entries.subspan(appended.size()),
      std::span<const std::string>(data).subspan(appended.size()));
  if (!rest.ok()) {
    if (appended.empty()) return rest.status();
    return absl::Status(rest.status().code(),
                        absl::StrCat(rest.status().message(),
                                     " (after the first, which it holds)"));
  }
  appended.insert(appended.end(), rest->begin(), rest->end());
  return appended;
}

namespace {

// What an append of several entries did: each entry's place in the log, or
// the first error and which of them the log holds (by position from 1).
absl::StatusOr<std::vector<engine::AppendedEntry>> Outcomes(
    std::string_view fleet_id,
    const std::vector<std::optional<absl::StatusOr<engine::AppendedEntry>>>&
        results) {
  std::vector<engine::AppendedEntry> appended;
  std::vector<size_t> held;
  absl::Status first_error;
  for (size_t i = 0; i < results.size(); ++i) {
    const absl::StatusOr<engine::AppendedEntry> none =
        absl::DeadlineExceededError(
            absl::StrCat("cluster: appending to the log of fleet \"",
                         V(fleet_id), "\": not sent, or no acknowledgement"));
    const absl::StatusOr<engine::AppendedEntry>& result =
        results[i].has_value() ? *results[i] : none;
    if (result.ok()) {
      appended.push_back(*result);
      held.push_back(i + 1);
    } else if (first_error.ok()) {
      first_error = result.status();
    }
  }
  if (first_error.ok()) return appended;
  return absl::Status(
      first_error.code(),
      absl::StrCat(first_error.message(), "; the log holds ", held.size(),
                   " of these ", results.size(), " entries",
                   held.empty()
                       ? std::string()
                       : absl::StrCat(" (", absl::StrJoin(held, ", "), ")")));
}

}  // namespace

absl::StatusOr<std::vector<engine::AppendedEntry>>
NatsFleetLog::AppendPipelined(std::string_view fleet_id,
                              std::span<const engine::LogAppend> entries,
                              std::span<const std::string> data) {
  const int64_t max_payload = natsConnection_GetMaxPayload(handles_->nc);
  for (const std::string& one : data) {
    if (max_payload > 0 && static_cast<int64_t>(one.size()) > max_payload) {
      return absl::InvalidArgumentError(absl::StrCat(
          "cluster: an entry of ", one.size(), " bytes exceeds NATS's ",
          max_payload,
          "-byte message limit (max_payload); send smaller batches; nothing "
          "was appended"));
    }
  }
  if (absl::Status ready = EnsureStream(fleet_id); !ready.ok()) return ready;
  const std::string subject = FleetSubject(fleet_id);
  const std::string stream = FleetStreamName(fleet_id);
  AsyncAcks& acks = handles_->acks;
  std::vector<std::optional<absl::StatusOr<engine::AppendedEntry>>> results(
      entries.size());
  size_t waiting = 0;  // guarded by acks.mu
  std::vector<const natsMsg*> sent;
  // Published in order on one connection: JetStream numbers them so.
  for (size_t i = 0; i < entries.size(); ++i) {
    natsMsg* msg = nullptr;
    natsStatus s =
        natsMsg_Create(&msg, subject.c_str(), nullptr, data[i].data(),
                       static_cast<int>(data[i].size()));
    const std::string msg_id(entries[i].id);
    jsPubOptions publish;
    jsPubOptions_Init(&publish);
    if (!msg_id.empty()) publish.MsgId = msg_id.c_str();
    publish.ExpectStream = stream.c_str();
    publish.MaxWait = Milliseconds(options_.timeout);
    if (s == NATS_OK) {
      // Its slot before it is sent: the acknowledgement may come first.
      absl::MutexLock lock(&acks.mu);
      acks.slots[msg] = AsyncAcks::Slot{&results[i], &waiting};
      ++waiting;
      sent.push_back(msg);
    }
    const natsMsg* published = msg;
    if (s == NATS_OK) {
      s = js_PublishMsgAsync(handles_->async_js, &msg, &publish);
    }
    natsMsg_Destroy(msg);  // nothing when nats.c took it
    if (s != NATS_OK) {
      // Not sent: this entry and those after it are not appended.
      absl::MutexLock lock(&acks.mu);
      auto it = acks.slots.find(published);
      if (it != acks.slots.end() && it->second.waiting == &waiting) {
        acks.slots.erase(it);
        --waiting;
      }
      results[i] =
          FromNats(s, 0,
                   absl::StrCat("cluster: appending to the log of fleet \"",
                                V(fleet_id), "\""));
      break;
    }
  }
  {
    // Every entry sent is acknowledged or timed out by nats.c (MaxWait);
    // the deadline is a guard.
    const absl::Time deadline =
        absl::Now() + options_.timeout + absl::Seconds(1);
    absl::MutexLock lock(&acks.mu);
    while (waiting > 0 && !acks.acked.WaitWithDeadline(&acks.mu, deadline)) {
    }
    // Those not acknowledged by now (a message's address may be another
    // append's by now: only this one's slots go).
    for (const natsMsg* msg : sent) {
      auto it = acks.slots.find(msg);
      if (it != acks.slots.end() && it->second.waiting == &waiting) {
        acks.slots.erase(it);
      }
    }
  }
  return Outcomes(fleet_id, results);
}

absl::StatusOr<engine::AppendedEntry> NatsFleetLog::AppendOne(
    std::string_view fleet_id, std::string_view id, std::string_view data,
    bool only_first) {
  const int64_t max_payload = natsConnection_GetMaxPayload(handles_->nc);
  if (max_payload > 0 && static_cast<int64_t>(data.size()) > max_payload) {
    return absl::InvalidArgumentError(absl::StrCat(
        "cluster: an entry of ", data.size(), " bytes exceeds NATS's ",
        max_payload,
        "-byte message limit (max_payload); send smaller batches"));
  }
  if (absl::Status ready = EnsureStream(fleet_id); !ready.ok()) return ready;
  const std::string subject = FleetSubject(fleet_id);
  const std::string stream = FleetStreamName(fleet_id);
  const std::string msg_id(id);
  jsPubOptions publish;
  jsPubOptions_Init(&publish);
  // No id: no deduplication (a call's entry, never a retry of another).
  if (!msg_id.empty()) publish.MsgId = msg_id.c_str();
  publish.ExpectStream = stream.c_str();
  publish.MaxWait = Milliseconds(options_.timeout);
  // The log has one subject: no message on it means an empty log.
  publish.ExpectNoMessage = only_first;
  jsPubAck* ack = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus s =
      js_Publish(&ack, handles_->js, subject.c_str(), data.data(),
                 static_cast<int>(data.size()), &publish, &code);
  if (s != NATS_OK && only_first && code == JSStreamWrongLastSequenceErr) {
    return absl::FailedPreconditionError(
        absl::StrCat("cluster: the log of fleet \"", V(fleet_id),
                     "\" has entries already (created meanwhile)"));
  }
  if (s != NATS_OK) {
    return FromNats(s, code,
                    absl::StrCat("cluster: appending to the log of "
                                 "fleet \"",
                                 V(fleet_id), "\""));
  }
  const engine::AppendedEntry appended{ack->Sequence, ack->Duplicate};
  jsPubAck_Destroy(ack);
  return appended;
}

absl::StatusOr<engine::LogBounds> NatsFleetLog::Bounds(
    std::string_view fleet_id) {
  jsStreamInfo* info = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const std::string name = FleetStreamName(fleet_id);
  const natsStatus s =
      js_GetStreamInfo(&info, handles_->js, name.c_str(), nullptr, &code);
  if (s == NATS_NOT_FOUND || code == JSStreamNotFoundErr) {
    return engine::LogBounds{};
  }
  if (s != NATS_OK) {
    return FromNats(
        s, code,
        absl::StrCat("cluster: the log of fleet \"", V(fleet_id), "\""));
  }
  // JetStream reports {0, 0} for a stream that never held a message, and
  // {last + 1, last} for one purged whole.
  const engine::LogBounds bounds{info->State.FirstSeq, info->State.LastSeq};
  jsStreamInfo_Destroy(info);
  return bounds;
}

absl::Status NatsFleetLog::PurgeBelow(const std::string& stream,
                                      uint64_t sequence) {
  jsStreamInfo* info = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  natsStatus s =
      js_GetStreamInfo(&info, handles_->js, stream.c_str(), nullptr, &code);
  if (s != NATS_OK) {
    return FromNats(s, code, absl::StrCat("cluster: stream ", stream));
  }
  const uint64_t first = info->State.FirstSeq;
  const uint64_t last = info->State.LastSeq;
  jsStreamInfo_Destroy(info);
  // Nothing below it, or past the end: JetStream 2.9 purges every message
  // when asked to purge below its first sequence (seen with 1).
  if (sequence <= first || sequence > last + 1) return absl::OkStatus();
  jsOptions options;
  jsOptions_Init(&options);
  options.Wait = Milliseconds(options_.timeout);
  options.Stream.Purge.Sequence = sequence;  // up to, not including
  code = static_cast<jsErrCode>(0);
  s = js_PurgeStream(handles_->js, stream.c_str(), &options, &code);
  if (s != NATS_OK) {
    return FromNats(
        s, code,
        absl::StrCat("cluster: purging stream ", stream, " below ", sequence));
  }
  return absl::OkStatus();
}

absl::Status NatsFleetLog::Trim(std::string_view fleet_id, uint64_t through) {
  absl::Status status = PurgeBelow(FleetStreamName(fleet_id), through + 1);
  if (status.ok()) return status;
  return absl::Status(status.code(),
                      absl::StrCat("trimming the log of fleet \"", V(fleet_id),
                                   "\": ", status.message()));
}

absl::StatusOr<std::vector<std::string>> NatsFleetLog::Fleets() {
  // Names only (the meta leader answers them alone; listing every stream's
  // info waits on each stream's leader, and times out while one is being
  // elected); a log's fleet id is read from its description once.
  jsStreamNamesList* list = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus s = js_StreamNames(&list, handles_->js, nullptr, &code);
  std::vector<std::string> fleets;
  if (s == NATS_NOT_FOUND) return fleets;  // no stream at all
  if (s != NATS_OK) {
    // JetStream electing its meta leader (seconds after a server is lost):
    // the logs seen so far (a log is never deleted by fleetmem).
    absl::MutexLock lock(&handles_->mu);
    if (!Unreachable(s) || handles_->fleet_of_log.empty()) {
      return FromNats(s, code, "cluster: listing the logs");
    }
    for (const auto& [name, fleet] : handles_->fleet_of_log) {
      fleets.push_back(fleet);
    }
    std::sort(fleets.begin(), fleets.end());
    return fleets;
  }
  std::vector<std::string> names;
  const size_t log_name_size = FleetStreamName("").size();
  for (int i = 0; i < list->Count; ++i) {
    const std::string name = list->List[i] != nullptr ? list->List[i] : "";
    // Logs only: FLEETMEM_ and 16 hex digits (not FLEETMEM_SNAP_...).
    if (name.size() == log_name_size && absl::StartsWith(name, "FLEETMEM_") &&
        name.find_first_not_of("0123456789abcdef", 9) == std::string::npos) {
      names.push_back(name);
    }
  }
  jsStreamNamesList_Destroy(list);
  for (const std::string& name : names) {
    {
      absl::MutexLock lock(&handles_->mu);
      auto known = handles_->fleet_of_log.find(name);
      if (known != handles_->fleet_of_log.end()) {
        fleets.push_back(known->second);
        continue;
      }
    }
    jsStreamInfo* info = nullptr;
    code = static_cast<jsErrCode>(0);
    if (js_GetStreamInfo(&info, handles_->js, name.c_str(), nullptr, &code) !=
        NATS_OK) {
      continue;  // its leader is being elected: next round
    }
    const std::string description =
        info->Config != nullptr && info->Config->Description != nullptr
            ? info->Config->Description
            : "";
    jsStreamInfo_Destroy(info);
    // Only the streams this module made: the name is the description's.
    if (description.empty() || FleetStreamName(description) != name) continue;
    absl::MutexLock lock(&handles_->mu);
    handles_->fleet_of_log[name] = description;
    fleets.push_back(description);
  }
  std::sort(fleets.begin(), fleets.end());
  return fleets;
}

namespace {

// OUT_OF_RANGE: entry `wanted` of the fleet's log was trimmed (a snapshot
// holds it); the log starts at `first`.
absl::Status TrimmedBefore(std::string_view fleet_id, uint64_t first,
                           uint64_t wanted) {
  return absl::OutOfRangeError(absl::StrCat(
      "cluster: the log of fleet \"", V(fleet_id), "\" starts at entry ", first,
      ", after entry ", wanted, " (trimmed: a snapshot holds it)"));
}

}  // namespace

absl::StatusOr<std::vector<engine::LogEntry>> NatsFleetLog::Read(
    std::string_view fleet_id, uint64_t after, size_t max) {
  const uint64_t from = after + 1;
  absl::StatusOr<engine::LogBounds> bounds = Bounds(fleet_id);
  if (!bounds.ok()) return bounds.status();
  const uint64_t* last = &bounds->last;
  // Entries before the first held were trimmed (a snapshot holds them) or
  // never stored (a failed proposal): never passed silently.
  if (bounds->last > 0 && from < bounds->first) {
    return TrimmedBefore(fleet_id, bounds->first, from);
  }
  // One get per entry from the stream's leader (JetStream's STREAM.MSG.GET:
  // it sees every acknowledged entry) up to the last sequence. No consumer:
  // creating one per read costs a round of the cluster's consensus. A
  // clustered stream may skip a sequence (a proposal that failed when its
  // leader changed): a sequence up to the last with no entry is passed.
  const std::string stream = FleetStreamName(fleet_id);
  std::vector<engine::LogEntry> entries;
  for (uint64_t sequence = from; sequence <= *last && entries.size() < max;
       ++sequence) {
    natsMsg* msg = nullptr;
    jsErrCode code = static_cast<jsErrCode>(0);
    natsStatus s =
        js_GetMsg(&msg, handles_->js, stream.c_str(), sequence, nullptr, &code);
    if (s == NATS_NOT_FOUND || code == JSNoMessageFoundErr) {
      // Trimmed since the bounds were read (the previous owner's snapshot
      // writer, late, purging what its snapshot covers)? Then the entry is
      // in a snapshot, not skipped: OUT_OF_RANGE, and the caller restores.
      // Passing it would lose it on this replica (seen: an owner holding
      // one entry fewer than the log, docs/distributed.md).
      absl::StatusOr<engine::LogBounds> now = Bounds(fleet_id);
      if (!now.ok() || sequence < now->first) {
        if (!entries.empty()) break;  // what was read; the next read says so
        if (!now.ok()) return now.status();
        return TrimmedBefore(fleet_id, now->first, sequence);
      }
      // A sequence JetStream skipped (a proposal that failed as its leader
      // changed): said, never passed silently.
      FLEETMEM_LOG(kWarning)
          << "cluster: the log of fleet \"" << fleet_id << "\" has no entry "
          << sequence << " (of " << now->first << ".." << now->last
          << "; JetStream: " << natsStatus_GetText(s) << ", code "
          << static_cast<int>(code) << "): passed";
      continue;
    }
    if (s != NATS_OK) {
      if (!entries.empty()) break;  // what was read; the next read retries
      return FromNats(
          s, code,
          absl::StrCat("cluster: reading entry ", sequence,
                       " of the log of fleet \"", V(fleet_id), "\""));
    }
    engine::LogEntry entry;
    entry.sequence = sequence;
    const char* id = nullptr;
    if (natsMsgHeader_Get(msg, "Nats-Msg-Id", &id) == NATS_OK &&
        id != nullptr) {
      entry.id = id;
    }
    absl::StatusOr<engine::StoredRecord> record = DecodeRecord(
        fleet_id, sequence,
        std::string_view(natsMsg_GetData(msg), natsMsg_GetDataLength(msg)));
    natsMsg_Destroy(msg);
    if (!record.ok()) {
      // Never passed: the entries before it are applied, then it stops
      // the fleet's log (said in the log) until a version that knows it.
      if (!entries.empty()) break;
      return record.status();
    }
    entry.record = *std::move(record);
    entries.push_back(std::move(entry));
  }
  return entries;
}

absl::StatusOr<Lease> NatsFleetLog::Acquire(std::string_view fleet_id,
                                            std::string_view owner) {
  if (owner.empty()) {
    return absl::InvalidArgumentError("cluster: a lease needs an owner");
  }
  const std::string key = FleetLeaseKey(fleet_id);
  const std::string value = absl::StrCat(V(owner), "\n", V(fleet_id));
  uint64_t revision = 0;
  natsStatus s = kvStore_Create(&revision, handles_->kv, key.c_str(),
                                value.data(), static_cast<int>(value.size()));
  if (s == NATS_OK) {
    return Lease{std::string(fleet_id), std::string(owner), revision};
  }
  if (Unreachable(s)) return FromNats(s, 0, "cluster: taking a lease");
  // The key exists: held, or released (an empty value, which is taken over
  // at its revision, so two replicas cannot both take it).
  kvEntry* entry = nullptr;
  s = kvStore_Get(&entry, handles_->kv, key.c_str());
  if (s != NATS_OK) {
    return FromNats(
        s, 0,
        absl::StrCat("cluster: the lease of fleet \"", V(fleet_id), "\""));
  }
  const std::string held(static_cast<const char*>(kvEntry_Value(entry)),
                         kvEntry_ValueLen(entry));
  const uint64_t last = kvEntry_Revision(entry);
  kvEntry_Destroy(entry);
  // Held by this owner (a restarted replica: its id is its own): taken
  // over at its revision, without waiting for it to expire.
  if (!held.empty() && held != value) {
    return absl::FailedPreconditionError(absl::StrCat(
        "cluster: fleet \"", V(fleet_id), "\" is owned by ",
        held.substr(0, held.find('\n')), " (lease revision ", last, ")"));
  }
  s = kvStore_Update(&revision, handles_->kv, key.c_str(), value.data(),
                     static_cast<int>(value.size()), last);
  if (s == NATS_OK) {
    return Lease{std::string(fleet_id), std::string(owner), revision};
  }
  if (Unreachable(s)) return FromNats(s, 0, "cluster: taking a lease");
  return absl::FailedPreconditionError(
      absl::StrCat("cluster: fleet \"", V(fleet_id),
                   "\" was taken by another replica meanwhile"));
}

absl::StatusOr<Lease> NatsFleetLog::Renew(const Lease& lease) {
  const std::string key = FleetLeaseKey(lease.fleet_id);
  const std::string value = absl::StrCat(lease.owner, "\n", lease.fleet_id);
  uint64_t revision = 0;
  const natsStatus s =
      kvStore_Update(&revision, handles_->kv, key.c_str(), value.data(),
                     static_cast<int>(value.size()), lease.revision);
  if (s == NATS_OK) return Lease{lease.fleet_id, lease.owner, revision};
  if (Unreachable(s)) return FromNats(s, 0, "cluster: renewing a lease");
  return absl::FailedPreconditionError(
      absl::StrCat("cluster: the lease of fleet \"", lease.fleet_id,
                   "\" at revision ", lease.revision, " was lost"));
}

absl::Status NatsFleetLog::Release(const Lease& lease) {
  // An empty value at the lease's revision: released, and no one else's
  // lease can be dropped by a late Release.
  const std::string key = FleetLeaseKey(lease.fleet_id);
  uint64_t revision = 0;
  const natsStatus s = kvStore_Update(&revision, handles_->kv, key.c_str(), "",
                                      0, lease.revision);
  if (s == NATS_OK) return absl::OkStatus();
  if (Unreachable(s)) return FromNats(s, 0, "cluster: releasing a lease");
  return absl::FailedPreconditionError(
      absl::StrCat("cluster: the lease of fleet \"", lease.fleet_id,
                   "\" at revision ", lease.revision, " was lost already"));
}

absl::StatusOr<std::optional<Lease>> NatsFleetLog::Holder(
    std::string_view fleet_id) {
  const std::string key = FleetLeaseKey(fleet_id);
  kvEntry* entry = nullptr;
  const natsStatus s = kvStore_Get(&entry, handles_->kv, key.c_str());
  if (s == NATS_NOT_FOUND) return std::optional<Lease>();
  if (s != NATS_OK) {
    return FromNats(
        s, 0,
        absl::StrCat("cluster: the lease of fleet \"", V(fleet_id), "\""));
  }
  const std::string value(static_cast<const char*>(kvEntry_Value(entry)),
                          kvEntry_ValueLen(entry));
  Lease lease{std::string(fleet_id), value.substr(0, value.find('\n')),
              kvEntry_Revision(entry)};
  kvEntry_Destroy(entry);
  if (lease.owner.empty()) return std::optional<Lease>();  // released
  return std::optional<Lease>(std::move(lease));
}

struct NatsFleetLog::LatestMeta {
  cluster::v1::SnapshotMeta meta;
  uint64_t stream_sequence = 0;
};

absl::StatusOr<std::optional<NatsFleetLog::LatestMeta>> NatsFleetLog::ReadMeta(
    std::string_view fleet_id) {
  const std::string stream = SnapshotStreamName(fleet_id);
  const std::string subject = absl::StrCat(SnapshotSubject(fleet_id), ".meta");
  jsErrCode code = static_cast<jsErrCode>(0);
  // The stream's state first: a message get on a stream that another
  // replica is making (its first snapshot) crashes nats-server 2.9.10 (its
  // store is not set yet: a nil dereference in jsMsgGetRequest, seen in the
  // owner-loss case, docs/distributed.md), while its state reads as empty.
  jsStreamInfo* info = nullptr;
  natsStatus s =
      js_GetStreamInfo(&info, handles_->js, stream.c_str(), nullptr, &code);
  if (s == NATS_NOT_FOUND || code == JSStreamNotFoundErr) {
    return std::optional<LatestMeta>();
  }
  if (s != NATS_OK) {
    return FromNats(
        s, code,
        absl::StrCat("cluster: the snapshot of fleet \"", V(fleet_id), "\""));
  }
  const uint64_t messages = info->State.Msgs;
  jsStreamInfo_Destroy(info);
  if (messages == 0) return std::optional<LatestMeta>();
  natsMsg* msg = nullptr;
  s = js_GetLastMsg(&msg, handles_->js, stream.c_str(), subject.c_str(),
                    nullptr, &code);
  if (s == NATS_NOT_FOUND || code == JSNoMessageFoundErr ||
      code == JSStreamNotFoundErr) {
    return std::optional<LatestMeta>();
  }
  if (s != NATS_OK) {
    return FromNats(
        s, code,
        absl::StrCat("cluster: the snapshot of fleet \"", V(fleet_id), "\""));
  }
  LatestMeta latest;
  latest.stream_sequence = natsMsg_GetSequence(msg);
  const bool parsed = latest.meta.ParseFromArray(natsMsg_GetData(msg),
                                                 natsMsg_GetDataLength(msg));
  natsMsg_Destroy(msg);
  if (!parsed) {
    return absl::DataLossError(
        absl::StrCat("cluster: the snapshot description of fleet \"",
                     V(fleet_id), "\" does not parse"));
  }
  return std::optional<LatestMeta>(std::move(latest));
}

namespace {

// Publishes one part of a snapshot (a chunk, or its description last)
// under `snapshot_id`; FAILED_PRECONDITION if `options` expected another
// last description (a snapshot stored meanwhile). Sets the part's stream
// sequence.
absl::Status PublishSnapshotPart(jsCtx* js, std::string_view fleet_id,
                                 const std::string& subject,
                                 std::string_view data,
                                 const std::string& snapshot_id,
                                 jsPubOptions options, uint64_t* sequence) {
  natsMsg* msg = nullptr;
  natsStatus s = natsMsg_Create(&msg, subject.c_str(), nullptr, data.data(),
                                static_cast<int>(data.size()));
  if (s == NATS_OK) {
    s = natsMsgHeader_Set(msg, "Fleetmem-Snapshot", snapshot_id.c_str());
  }
  jsPubAck* ack = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  if (s == NATS_OK) s = js_PublishMsg(&ack, js, msg, &options, &code);
  natsMsg_Destroy(msg);
  if (s != NATS_OK) {
    if (code == JSStreamWrongLastSequenceErr) {
      return absl::FailedPreconditionError(
          absl::StrCat("cluster: another snapshot of fleet \"", V(fleet_id),
                       "\" was stored meanwhile"));
    }
    return FromNats(s, code,
                    absl::StrCat("cluster: storing a snapshot of fleet \"",
                                 V(fleet_id), "\""));
  }
  *sequence = ack->Sequence;
  jsPubAck_Destroy(ack);
  return absl::OkStatus();
}

}  // namespace

absl::Status NatsFleetLog::Put(std::string_view fleet_id,
                               const SnapshotInfo& info,
                               std::string_view image) {
  if (absl::Status ready = EnsureSnapshotStream(fleet_id); !ready.ok()) {
    return ready;
  }
  absl::StatusOr<std::optional<LatestMeta>> before = ReadMeta(fleet_id);
  if (!before.ok() && !absl::IsDataLoss(before.status())) {
    return before.status();
  }
  const bool has_before = before.ok() && before->has_value();
  if (has_before && (*before)->meta.sequence() >= info.sequence) {
    return absl::FailedPreconditionError(absl::StrCat(
        "cluster: fleet \"", V(fleet_id), "\" has a snapshot through ",
        (*before)->meta.sequence(), " already"));
  }
  const std::string stream = SnapshotStreamName(fleet_id);
  const std::string chunk_subject =
      absl::StrCat(SnapshotSubject(fleet_id), ".chunk");
  const std::string meta_subject =
      absl::StrCat(SnapshotSubject(fleet_id), ".meta");
  cluster::v1::SnapshotMeta meta;
  meta.set_sequence(info.sequence);
  meta.set_bytes(image.size());
  meta.set_code_dimension(info.code_dimension);
  meta.set_encoder_version(info.encoder_version);
  meta.set_id(absl::StrCat(info.sequence, "-", absl::ToUnixNanos(absl::Now())));
  meta.set_xxh3(XXH3_64bits(image.data(), image.size()));
  // Chunks well under NATS's max_payload (1 MiB by default).
  const int64_t max_payload = natsConnection_GetMaxPayload(handles_->nc);
  const size_t chunk_bytes = static_cast<size_t>(std::clamp<int64_t>(
      max_payload > 0 ? max_payload - 4096 : 0, 4096, 512 * 1024));
  jsPubOptions chunk_options;
  jsPubOptions_Init(&chunk_options);
  chunk_options.ExpectStream = stream.c_str();
  chunk_options.MaxWait = Milliseconds(options_.timeout);
  size_t offset = 0;
  do {
    const std::string_view chunk = image.substr(offset, chunk_bytes);
    uint64_t sequence = 0;
    if (absl::Status sent =
            PublishSnapshotPart(handles_->js, fleet_id, chunk_subject, chunk,
                                meta.id(), chunk_options, &sequence);
        !sent.ok()) {
      return sent;
    }
    if (meta.chunks() == 0) meta.set_first_chunk(sequence);
    meta.set_last_chunk(sequence);
    meta.set_chunks(meta.chunks() + 1);
    offset += chunk.size();
  } while (offset < image.size());
  // The description last, and only over the one read above.
  jsPubOptions meta_options = chunk_options;
  if (has_before) {
    meta_options.ExpectLastSubjectSeq = (*before)->stream_sequence;
  } else if (before.ok()) {
    meta_options.ExpectNoMessage = true;
  }  // else a damaged description: replaced unconditionally
  uint64_t meta_sequence = 0;
  if (absl::Status sent = PublishSnapshotPart(
          handles_->js, fleet_id, meta_subject, meta.SerializeAsString(),
          meta.id(), meta_options, &meta_sequence);
      !sent.ok()) {
    return sent;
  }
  // Earlier snapshots (and chunks of failed ones) go.
  if (absl::Status purged = PurgeBelow(stream, meta.first_chunk());
      !purged.ok()) {
    return absl::Status(
        purged.code(),
        absl::StrCat(
            "cluster: the snapshot of fleet \"", V(fleet_id),
            "\" is stored; dropping the earlier one: ", purged.message()));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::optional<SnapshotInfo>> NatsFleetLog::Latest(
    std::string_view fleet_id) {
  absl::StatusOr<std::optional<LatestMeta>> latest = ReadMeta(fleet_id);
  if (!latest.ok()) return latest.status();
  if (!latest->has_value()) return std::optional<SnapshotInfo>();
  const cluster::v1::SnapshotMeta& meta = (*latest)->meta;
  return std::optional<SnapshotInfo>(SnapshotInfo{meta.sequence(), meta.bytes(),
                                                  meta.code_dimension(),
                                                  meta.encoder_version()});
}

absl::StatusOr<std::optional<std::pair<SnapshotInfo, std::string>>>
NatsFleetLog::Fetch(std::string_view fleet_id) {
  absl::StatusOr<std::optional<LatestMeta>> latest = ReadMeta(fleet_id);
  if (!latest.ok()) return latest.status();
  if (!latest->has_value()) {
    return std::optional<std::pair<SnapshotInfo, std::string>>();
  }
  const cluster::v1::SnapshotMeta& meta = (*latest)->meta;
  const std::string stream = SnapshotStreamName(fleet_id);
  const std::string chunk_subject =
      absl::StrCat(SnapshotSubject(fleet_id), ".chunk");
  std::string image;
  image.reserve(meta.bytes());
  uint32_t chunks = 0;
  for (uint64_t sequence = meta.first_chunk();
       sequence <= meta.last_chunk() && chunks < meta.chunks(); ++sequence) {
    natsMsg* msg = nullptr;
    jsErrCode code = static_cast<jsErrCode>(0);
    const natsStatus s =
        js_GetMsg(&msg, handles_->js, stream.c_str(), sequence, nullptr, &code);
    if (s == NATS_NOT_FOUND || code == JSNoMessageFoundErr) continue;
    if (s != NATS_OK) {
      return FromNats(s, code,
                      absl::StrCat("cluster: reading the snapshot of fleet \"",
                                   V(fleet_id), "\""));
    }
    const char* id = nullptr;
    // Only this snapshot's chunks (another replica's may sit between).
    if (chunk_subject == natsMsg_GetSubject(msg) &&
        natsMsgHeader_Get(msg, "Fleetmem-Snapshot", &id) == NATS_OK &&
        id != nullptr && meta.id() == id) {
      image.append(natsMsg_GetData(msg), natsMsg_GetDataLength(msg));
      ++chunks;
    }
    natsMsg_Destroy(msg);
  }
  if (chunks != meta.chunks() || image.size() != meta.bytes() ||
      XXH3_64bits(image.data(), image.size()) != meta.xxh3()) {
    return absl::DataLossError(absl::StrCat(
        "cluster: the snapshot of fleet \"", V(fleet_id), "\" through entry ",
        meta.sequence(), " is incomplete or damaged (", chunks, " of ",
        meta.chunks(), " chunks, ", image.size(), " of ", meta.bytes(),
        " bytes)"));
  }
  return std::optional<std::pair<SnapshotInfo, std::string>>(
      std::pair<SnapshotInfo, std::string>(
          SnapshotInfo{meta.sequence(), meta.bytes(), meta.code_dimension(),
                       meta.encoder_version()},
          std::move(image)));
}

absl::Status NatsFleetLog::Announce(std::string_view replica, uint64_t fleets) {
  if (replica.empty() || replica.find('\n') != std::string_view::npos) {
    return absl::InvalidArgumentError("cluster: a bad replica id");
  }
  const std::string key = absl::StrCat("replica.", Hash(replica));
  const std::string value = absl::StrCat(V(replica), "\n", fleets);
  uint64_t revision = 0;
  const natsStatus s =
      kvStore_Put(&revision, handles_->kv, key.c_str(), value.data(),
                  static_cast<int>(value.size()));
  if (s != NATS_OK) return FromNats(s, 0, "cluster: announcing this replica");
  return absl::OkStatus();
}

absl::StatusOr<std::vector<std::pair<std::string, uint64_t>>>
NatsFleetLog::Replicas() {
  // The bucket's subjects under replica.: from its stream's state (the
  // stream leader answers; listing keys would create a consumer).
  const std::string stream = absl::StrCat("KV_", options_.lease_bucket);
  const std::string prefix =
      absl::StrCat("$KV.", options_.lease_bucket, ".replica.");
  const std::string filter = absl::StrCat(prefix, ">");
  jsOptions options;
  jsOptions_Init(&options);
  options.Wait = Milliseconds(options_.timeout);
  options.Stream.Info.SubjectsFilter = filter.c_str();
  jsStreamInfo* info = nullptr;
  jsErrCode code = static_cast<jsErrCode>(0);
  const natsStatus s =
      js_GetStreamInfo(&info, handles_->js, stream.c_str(), &options, &code);
  if (s != NATS_OK) {
    return FromNats(s, code, "cluster: listing the replicas");
  }
  std::vector<std::string> keys;
  if (info->State.Subjects != nullptr) {
    for (int i = 0; i < info->State.Subjects->Count; ++i) {
      const char* subject = info->State.Subjects->List[i].Subject;
      if (subject != nullptr && absl::StartsWith(subject, prefix)) {
        keys.push_back(
            std::string(subject).substr(std::string_view("$KV.").size() +
                                        options_.lease_bucket.size() + 1));
      }
    }
  }
  jsStreamInfo_Destroy(info);
  std::vector<std::pair<std::string, uint64_t>> replicas;
  for (const std::string& key : keys) {
    kvEntry* entry = nullptr;
    const natsStatus got = kvStore_Get(&entry, handles_->kv, key.c_str());
    if (got == NATS_NOT_FOUND) continue;  // expired meanwhile
    if (got != NATS_OK) return FromNats(got, 0, "cluster: reading a replica");
    const std::string value(static_cast<const char*>(kvEntry_Value(entry)),
                            kvEntry_ValueLen(entry));
    kvEntry_Destroy(entry);
    const size_t newline = value.find('\n');
    uint64_t fleets = 0;
    if (newline == std::string::npos ||
        !absl::SimpleAtoi(value.substr(newline + 1), &fleets)) {
      continue;  // not an announcement of this version
    }
    replicas.emplace_back(value.substr(0, newline), fleets);
  }
  std::sort(replicas.begin(), replicas.end());
  return replicas;
}

}  // namespace fleetmem::cluster
