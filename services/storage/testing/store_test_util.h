// Helpers for the MemoryStore tests: sample records, a canonical text dump
// for exact comparison, a scripted workload and a temporary directory.
#ifndef FLEETMEM_SERVICES_STORAGE_TESTING_STORE_TEST_UTIL_H_
#define FLEETMEM_SERVICES_STORAGE_TESTING_STORE_TEST_UTIL_H_

#include <cstdint>
#include <string>
#include <vector>

#include "services/common/files.h"
#include "services/core/seq_set.h"
#include "services/core/types.h"
#include "services/engine/memory_store.h"

namespace fleetmem::storage::testing {

// A trace whose every field depends on (robot_id, seq), cluster_id 0.
core::MemoryTrace MakeTrace(const std::string& robot_id, uint64_t seq);

// Cluster `id` of `robot_id` with the traces (robot_id, seq) for `seqs`, in
// that order; cluster_id set on each.
core::Cluster MakeCluster(uint64_t id, const std::string& robot_id,
                          const std::vector<uint64_t>& seqs);

core::MemoryEvent MakeEvent(uint64_t id, core::EventType type,
                            uint64_t cluster_id);

engine::RobotRecord MakeRobot(const std::string& robot_id,
                              const std::vector<core::SeqSet::Interval>& seqs,
                              uint64_t replayed);

engine::FleetMeta MakeMeta(uint64_t consolidations);

// Every field, floats in hexadecimal: equal dumps mean equal records.
std::string Dump(const engine::FleetRecord& record);
std::string Dump(const std::vector<core::MemoryEvent>& events);

// `count` mutations of one fleet shaped like the engine's: uploads of pending
// traces from three robots, consolidations into clusters with events,
// replay-count updates, forgetting, single-trace erasure.
std::vector<engine::FleetMutation> ScriptedMutations(int count);

// A fresh directory under $TMPDIR (or /tmp), removed with its contents on
// destruction (the project's one helper, services/common/files.h).
using TempDir = files::TempDir;

}  // namespace fleetmem::storage::testing

#endif  // FLEETMEM_SERVICES_STORAGE_TESTING_STORE_TEST_UTIL_H_
