// The clusters of a fleet's static memory as its index snapshot carries
// them (the memory image): each cluster's id, robot and centroid (as the
// store holds it: memory keeps it in forgetting's tracker), and every
// field of its traces but the code, which the snapshot's index holds. A
// load after a clean stop takes the clusters from here rather than read
// every trace record and cluster from the store
// (MemoryStore::IndexSnapshotCurrent says when it may). Strings that repeat
// (robot ids, domains, encoder versions) are written once, in a table:
//   length of what follows (u64)
//   | "MIM1" | strings: count (u32), each: length (u64), bytes
//   | clusters: count (u64), each:
//       id (u64) | robot (u32, into the table) | centroid: n (u32), floats
//       | traces: n (u32), each: robot (u32) | seq (u64) | domain (u32)
//         | encoder version (u32) | x, y, z, yaw (f64) | reward, external,
//         internal (f32) | timestamp (i64) | replay count (u32)
//         | attachment: n (u32), bytes
// in the host's byte order (the snapshot's index is too).
#ifndef FLEETMEM_SERVICES_ENGINE_MEMORY_IMAGE_H_
#define FLEETMEM_SERVICES_ENGINE_MEMORY_IMAGE_H_

#include <cstdint>
#include <functional>
#include <map>
#include <span>
#include <vector>

#include "absl/status/statusor.h"
#include "services/core/byte_stream.h"
#include "services/core/types.h"

namespace fleetmem::engine {

// Writes `clusters` (a static memory's, by id) without their traces' codes,
// each with the centroid `centroid_of(id)` gives.
void SaveMemoryImage(
    const std::map<uint64_t, core::Cluster>& clusters,
    const std::function<std::span<const float>(uint64_t)>& centroid_of,
    core::ByteWriter& out);

// The clusters SaveMemoryImage wrote (after its length, which the caller
// has read), in id order, each trace's cluster_id set and its code empty;
// DATA_LOSS if the bytes are not such an image (truncated, a string out of
// its table, a length past the end).
absl::StatusOr<std::vector<core::Cluster>> LoadMemoryImage(
    core::ByteReader& in);

}  // namespace fleetmem::engine

#endif  // FLEETMEM_SERVICES_ENGINE_MEMORY_IMAGE_H_
