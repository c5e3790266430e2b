// Distributed mode's fleet aliases (engine/fleet_aliases.h): a NATS
// key-value bucket without a time-to-live (the lease bucket expires its
// keys; aliases must not), one key per alias ("alias." + its hash, the
// value "ALIAS\nFLEET"). Each replica follows the bucket with a watcher and
// resolves from its copy; its own changes reach its copy at once, another
// replica's within a round trip. Changes are compare-and-set on the key's
// revision, so two replicas switching one alias at once both succeed in
// some order, and a creation loses to an existing alias. Internal to
// services/cluster: NatsFleetLog::OpenAliases makes one.
#ifndef FLEETMEM_SERVICES_CLUSTER_NATS_ALIASES_H_
#define FLEETMEM_SERVICES_CLUSTER_NATS_ALIASES_H_

#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "nats/nats.h"
#include "services/engine/fleet_aliases.h"

namespace fleetmem::cluster {

class NatsAliases final : public engine::AliasTable {
 public:
  // Opens (makes if missing) `bucket` through `js`, which must outlive the
  // table, and reads every alias before it returns (within `timeout`).
  static absl::StatusOr<std::unique_ptr<NatsAliases>> Open(
      jsCtx* js, const std::string& bucket, int replicas,
      absl::Duration timeout);
  ~NatsAliases() override;

  std::optional<std::string> Resolve(std::string_view name) const override;
  absl::StatusOr<std::vector<engine::FleetAlias>> List() const override;
  absl::Status Create(std::string_view alias,
                      std::string_view fleet_id) override;
  absl::StatusOr<std::string> Switch(std::string_view alias,
                                     std::string_view fleet_id) override;
  absl::StatusOr<std::string> Delete(std::string_view alias) override;

 private:
  NatsAliases(kvStore* kv, kvWatcher* watcher);
  // Applies one of the bucket's entries to the copy.
  void Follow(kvEntry* entry) ABSL_LOCKS_EXCLUDED(mu_);
  // The watcher's loop, until the table is destroyed.
  void Watch();
  // The alias's entry: its fleet and revision; nullopt if it has none.
  struct Current {
    std::string fleet_id;
    uint64_t revision = 0;
  };
  absl::StatusOr<std::optional<Current>> Get(std::string_view alias);

  kvStore* const kv_;
  kvWatcher* const watcher_;
  mutable absl::Mutex mu_;
  // By alias, and the alias of each key (a deletion names the key only).
  std::map<std::string, std::string, std::less<>> aliases_ ABSL_GUARDED_BY(mu_);
  std::map<std::string, std::string, std::less<>> alias_of_key_
      ABSL_GUARDED_BY(mu_);
  std::thread watching_;
};

}  // namespace fleetmem::cluster

#endif  // FLEETMEM_SERVICES_CLUSTER_NATS_ALIASES_H_
