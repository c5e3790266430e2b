#include "services/engine/fleet_aliases.h"

#include <memory>
#include <utility>

#include "absl/strings/str_cat.h"
#include "services/core/absl_view.h"

namespace fleetmem::engine {

absl::StatusOr<std::unique_ptr<StoredAliases>> StoredAliases::Open(
    MemoryStore* store) {
  const bool durable = store != nullptr;
  absl::StatusOr<std::vector<FleetAlias>> stored =
      durable ? store->LoadAliases() : std::vector<FleetAlias>();
  if (!stored.ok()) return stored.status();
  std::unique_ptr<StoredAliases> table(new StoredAliases(store, durable));
  absl::MutexLock lock(&table->mu_);
  for (FleetAlias& alias : *stored) {
    table->aliases_[std::move(alias.alias)] = std::move(alias.fleet_id);
  }
  return table;
}

std::optional<std::string> StoredAliases::Resolve(std::string_view name) const {
  absl::ReaderMutexLock lock(&mu_);
  auto it = aliases_.find(name);
  if (it == aliases_.end()) return std::nullopt;
  return it->second;
}

absl::StatusOr<std::vector<FleetAlias>> StoredAliases::List() const {
  absl::ReaderMutexLock lock(&mu_);
  std::vector<FleetAlias> aliases;
  for (const auto& [alias, fleet_id] : aliases_) {
    aliases.push_back({alias, fleet_id});
  }
  return aliases;
}

absl::Status StoredAliases::Put(std::string_view alias,
                                std::string_view fleet_id) {
  if (durable_) {
    if (absl::Status stored = store_->PutAlias(alias, fleet_id); !stored.ok()) {
      return absl::Status(stored.code(),
                          absl::StrCat(stored.message(), "; alias \"", V(alias),
                                       "\" left as it was"));
    }
  }
  if (fleet_id.empty()) {
    aliases_.erase(std::string(alias));
  } else {
    aliases_[std::string(alias)] = std::string(fleet_id);
  }
  return absl::OkStatus();
}

absl::Status StoredAliases::Create(std::string_view alias,
                                   std::string_view fleet_id) {
  absl::MutexLock lock(&mu_);
  if (auto it = aliases_.find(alias); it != aliases_.end()) {
    return absl::AlreadyExistsError(
        absl::StrCat("alias \"", V(alias), "\" exists (it names fleet \"",
                     it->second, "\"): switch it with SwitchAlias"));
  }
  return Put(alias, fleet_id);
}

absl::StatusOr<std::string> StoredAliases::Replace(std::string_view alias,
                                                   std::string_view fleet_id) {
  absl::MutexLock lock(&mu_);
  auto it = aliases_.find(alias);
  if (it == aliases_.end()) {
    return absl::NotFoundError(
        absl::StrCat("alias \"", V(alias), "\" does not exist"));
  }
  std::string before = it->second;
  if (absl::Status put = Put(alias, fleet_id); !put.ok()) return put;
  return before;
}

absl::StatusOr<std::string> StoredAliases::Switch(std::string_view alias,
                                                  std::string_view fleet_id) {
  return Replace(alias, fleet_id);
}

absl::StatusOr<std::string> StoredAliases::Delete(std::string_view alias) {
  return Replace(alias, "");
}

}  // namespace fleetmem::engine
