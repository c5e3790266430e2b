#include "services/cluster/nats_aliases.h"

#include <utility>

#include "absl/strings/str_cat.h"
#include "services/cluster/nats_status.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"

namespace fleetmem::cluster {
namespace {

std::string AliasKey(std::string_view alias) {
  return absl::StrCat("alias.", Hash(alias));
}

std::string AliasValue(std::string_view alias, std::string_view fleet_id) {
  return absl::StrCat(V(alias), "\n", V(fleet_id));
}

// Tries of a compare-and-set that another replica's change overtook.
constexpr int kCasAttempts = 5;

}  // namespace

absl::StatusOr<std::unique_ptr<NatsAliases>> NatsAliases::Open(
    jsCtx* js, const std::string& bucket, int replicas,
    absl::Duration timeout) {
  kvStore* kv = nullptr;
  natsStatus s = js_KeyValue(&kv, js, bucket.c_str());
  if (s == NATS_NOT_FOUND) {
    kvConfig config;
    kvConfig_Init(&config);
    config.Bucket = bucket.c_str();
    config.Description = "fleetmem: fleet aliases (alias -> fleet id)";
    config.History = 1;
    config.Replicas = replicas;
    config.StorageType = js_FileStorage;
    const natsStatus created = js_CreateKeyValue(&kv, js, &config);
    s = created;
    if (created != NATS_OK) {
      // Made by another replica meanwhile?
      s = js_KeyValue(&kv, js, bucket.c_str());
      if (s == NATS_NOT_FOUND) {
        // Neither there nor made: a JetStream cluster still electing its
        // leaders, or with too few servers up for the bucket's copies
        // (the server's start retries UNAVAILABLE, as for the leases).
        return absl::UnavailableError(absl::StrCat(
            FromNats(
                created, 0,
                absl::StrCat("cluster: making the alias bucket '", bucket, "'"))
                .message(),
            "; it is still missing, JetStream may not be ready yet"));
      }
    }
  }
  if (s != NATS_OK) {
    return FromNats(s, 0,
                    absl::StrCat("cluster: the alias bucket '", bucket, "'"));
  }
  kvWatcher* watcher = nullptr;
  s = kvStore_WatchAll(&watcher, kv, nullptr);
  if (s != NATS_OK) {
    kvStore_Destroy(kv);
    return FromNats(s, 0, "cluster: watching the alias bucket");
  }
  std::unique_ptr<NatsAliases> table(new NatsAliases(kv, watcher));
  // Every alias there is, up to the marker (a null entry) after them.
  const absl::Time give_up = absl::Now() + timeout;
  while (true) {
    kvEntry* entry = nullptr;
    const int64_t left =
        std::max<int64_t>(1, absl::ToInt64Milliseconds(give_up - absl::Now()));
    s = kvWatcher_Next(&entry, watcher, left);
    if (s != NATS_OK) {
      return FromNats(s, 0, "cluster: reading the aliases");
    }
    if (entry == nullptr) break;
    table->Follow(entry);
  }
  table->watching_ = std::thread([t = table.get()] { t->Watch(); });
  return table;
}

NatsAliases::NatsAliases(kvStore* kv, kvWatcher* watcher)
    : kv_(kv), watcher_(watcher) {}

NatsAliases::~NatsAliases() {
  kvWatcher_Stop(watcher_);
  if (watching_.joinable()) watching_.join();
  kvWatcher_Destroy(watcher_);
  kvStore_Destroy(kv_);
}

void NatsAliases::Watch() {
  while (true) {
    kvEntry* entry = nullptr;
    const natsStatus s = kvWatcher_Next(&entry, watcher_, 250);
    if (s == NATS_TIMEOUT) continue;
    if (s != NATS_OK) {
      if (s != NATS_ILLEGAL_STATE) {  // stopped: the table is going
        FLEETMEM_LOG(kWarning) << FromNats(s, 0, "cluster: alias watcher");
      }
      return;
    }
    if (entry != nullptr) Follow(entry);
  }
}

void NatsAliases::Follow(kvEntry* entry) {
  const std::string key = kvEntry_Key(entry);
  const std::string value(static_cast<const char*>(kvEntry_Value(entry)),
                          kvEntry_ValueLen(entry));
  const kvOperation op = kvEntry_Operation(entry);
  kvEntry_Destroy(entry);
  absl::MutexLock lock(&mu_);
  if (op == kvOp_Put) {
    const size_t newline = value.find('\n');
    if (newline == std::string::npos) return;  // not ours
    std::string alias = value.substr(0, newline);
    aliases_[alias] = value.substr(newline + 1);
    alias_of_key_[key] = std::move(alias);
    return;
  }
  if (auto it = alias_of_key_.find(key); it != alias_of_key_.end()) {
    aliases_.erase(it->second);
    alias_of_key_.erase(it);
  }
}

std::optional<std::string> NatsAliases::Resolve(std::string_view name) const {
  absl::ReaderMutexLock lock(&mu_);
  auto it = aliases_.find(name);
  if (it == aliases_.end()) return std::nullopt;
  return it->second;
}

absl::StatusOr<std::vector<engine::FleetAlias>> NatsAliases::List() const {
  absl::ReaderMutexLock lock(&mu_);
  std::vector<engine::FleetAlias> aliases;
  for (const auto& [alias, fleet_id] : aliases_) {
    aliases.push_back({alias, fleet_id});
  }
  return aliases;
}

absl::StatusOr<std::optional<NatsAliases::Current>> NatsAliases::Get(
    std::string_view alias) {
  kvEntry* entry = nullptr;
  const natsStatus s = kvStore_Get(&entry, kv_, AliasKey(alias).c_str());
  if (s == NATS_NOT_FOUND) return std::optional<Current>();
  if (s != NATS_OK) {
    return FromNats(s, 0, absl::StrCat("cluster: alias \"", V(alias), "\""));
  }
  const std::string value(static_cast<const char*>(kvEntry_Value(entry)),
                          kvEntry_ValueLen(entry));
  Current current{value.substr(value.find('\n') + 1), kvEntry_Revision(entry)};
  kvEntry_Destroy(entry);
  return std::optional<Current>(std::move(current));
}

absl::Status NatsAliases::Create(std::string_view alias,
                                 std::string_view fleet_id) {
  const std::string value = AliasValue(alias, fleet_id);
  uint64_t revision = 0;
  const natsStatus s =
      kvStore_Create(&revision, kv_, AliasKey(alias).c_str(), value.data(),
                     static_cast<int>(value.size()));
  if (s != NATS_OK) {
    if (Unreachable(s)) {
      return FromNats(
          s, 0, absl::StrCat("cluster: creating alias \"", V(alias), "\""));
    }
    absl::StatusOr<std::optional<Current>> current = Get(alias);
    if (current.ok() && current->has_value()) {
      return absl::AlreadyExistsError(absl::StrCat(
          "alias \"", V(alias), "\" exists (it names fleet \"",
          (*current)->fleet_id, "\"): switch it with SwitchAlias"));
    }
    return FromNats(s, 0,
                    absl::StrCat("cluster: creating alias \"", V(alias), "\""));
  }
  absl::MutexLock lock(&mu_);
  aliases_[std::string(alias)] = std::string(fleet_id);
  alias_of_key_[AliasKey(alias)] = std::string(alias);
  return absl::OkStatus();
}

absl::StatusOr<std::string> NatsAliases::Switch(std::string_view alias,
                                                std::string_view fleet_id) {
  const std::string key = AliasKey(alias);
  const std::string value = AliasValue(alias, fleet_id);
  for (int attempt = 0; attempt < kCasAttempts; ++attempt) {
    absl::StatusOr<std::optional<Current>> current = Get(alias);
    if (!current.ok()) return current.status();
    if (!current->has_value()) {
      return absl::NotFoundError(
          absl::StrCat("alias \"", V(alias), "\" does not exist"));
    }
    uint64_t revision = 0;
    const natsStatus s =
        kvStore_Update(&revision, kv_, key.c_str(), value.data(),
                       static_cast<int>(value.size()), (*current)->revision);
    if (s == NATS_OK) {
      absl::MutexLock lock(&mu_);
      aliases_[std::string(alias)] = std::string(fleet_id);
      alias_of_key_[key] = std::string(alias);
      return (*current)->fleet_id;
    }
    if (Unreachable(s)) {
      return FromNats(s, 0,
                      absl::StrCat("cluster: switching alias \"", V(alias),
                                   "\" (unknown whether it "
                                   "switched: list it)"));
    }
  }
  return absl::AbortedError(absl::StrCat(
      "alias \"", V(alias), "\" was changed by others during each of ",
      kCasAttempts, " tries; nothing was switched: retry"));
}

absl::StatusOr<std::string> NatsAliases::Delete(std::string_view alias) {
  absl::StatusOr<std::optional<Current>> current = Get(alias);
  if (!current.ok()) return current.status();
  if (!current->has_value()) {
    return absl::NotFoundError(
        absl::StrCat("alias \"", V(alias), "\" does not exist"));
  }
  const std::string key = AliasKey(alias);
  const natsStatus s = kvStore_Delete(kv_, key.c_str());
  if (s != NATS_OK) {
    return FromNats(s, 0,
                    absl::StrCat("cluster: deleting alias \"", V(alias), "\""));
  }
  absl::MutexLock lock(&mu_);
  aliases_.erase(std::string(alias));
  alias_of_key_.erase(key);
  return (*current)->fleet_id;
}

}  // namespace fleetmem::cluster
