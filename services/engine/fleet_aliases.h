// Fleet aliases (docs/api.md, "Aliases and encoder migration"): names that
// every fleet's call accepts in place of a fleet id, each naming one fleet
// at a time and switched to another in one step. A call resolves its name
// once, at the edge (transport::MemoryApi, the upload and watch streams),
// so that it reads and writes one fleet from start to end: a switch
// between two calls moves the second, never half of one.
//
// The table is a port: embedded mode keeps it in the store beside the
// fleets (StoredAliases, below), distributed mode in a NATS key-value
// bucket every replica follows (cluster::NatsFleetLog).
#ifndef FLEETMEM_SERVICES_ENGINE_FLEET_ALIASES_H_
#define FLEETMEM_SERVICES_ENGINE_FLEET_ALIASES_H_

#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "services/engine/memory_store.h"

namespace fleetmem::engine {

// Thread-safe. Names are valid ids (core::ValidateId), checked by the
// caller, as is that an alias never names a fleet id or another alias.
class AliasTable {
 public:
  virtual ~AliasTable() = default;

  // The fleet `name` stands for now, or nullopt when it is no alias. Never
  // waits on I/O: distributed mode answers from its copy of the shared
  // table, which follows a change made on another replica within a
  // network round trip.
  virtual std::optional<std::string> Resolve(std::string_view name) const = 0;
  // Every alias and its fleet, sorted by alias.
  virtual absl::StatusOr<std::vector<FleetAlias>> List() const = 0;
  // Makes `alias` name `fleet_id`, durably; ALREADY_EXISTS (naming its
  // fleet) if the alias exists, nothing changed.
  virtual absl::Status Create(std::string_view alias,
                              std::string_view fleet_id) = 0;
  // Points an existing alias at `fleet_id` in one step; the fleet it named
  // before. NOT_FOUND if there is no such alias, nothing changed.
  virtual absl::StatusOr<std::string> Switch(std::string_view alias,
                                             std::string_view fleet_id) = 0;
  // Removes the alias; the fleet it named. NOT_FOUND if there is none.
  virtual absl::StatusOr<std::string> Delete(std::string_view alias) = 0;
};

// Embedded mode's table: in the store (MemoryStore::PutAlias), with a copy
// in memory that Resolve reads. Without a store (null) they live in memory
// only (tests).
class StoredAliases final : public AliasTable {
 public:
  // Reads the stored aliases; the store's error if it cannot (a store
  // that keeps none: UNIMPLEMENTED). `store`, if set, must outlive the
  // table.
  static absl::StatusOr<std::unique_ptr<StoredAliases>> Open(
      MemoryStore* store);

  std::optional<std::string> Resolve(std::string_view name) const override;
  absl::StatusOr<std::vector<FleetAlias>> List() const override;
  absl::Status Create(std::string_view alias,
                      std::string_view fleet_id) override;
  absl::StatusOr<std::string> Switch(std::string_view alias,
                                     std::string_view fleet_id) override;
  absl::StatusOr<std::string> Delete(std::string_view alias) override;

 private:
  StoredAliases(MemoryStore* store, bool durable)
      : store_(store), durable_(durable) {}
  // An existing alias set to `fleet_id` (empty: erased); the fleet it named.
  absl::StatusOr<std::string> Replace(std::string_view alias,
                                      std::string_view fleet_id)
      ABSL_LOCKS_EXCLUDED(mu_);
  // Stores alias → fleet_id (empty: erased), then sets the copy.
  absl::Status Put(std::string_view alias, std::string_view fleet_id)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  MemoryStore* const store_;
  const bool durable_;
  mutable absl::Mutex mu_;
  std::map<std::string, std::string, std::less<>> aliases_ ABSL_GUARDED_BY(mu_);
};

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_FLEET_ALIASES_H_
