// This process's CPU time, memory, descriptors and start time from /proc,
// for the standard process_* metrics (the names Prometheus's own client
// libraries export, so that dashboards made for them work).
#ifndef FLEETMEM_SERVICES_OBSERVABILITY_PROCESS_STATS_H_
#define FLEETMEM_SERVICES_OBSERVABILITY_PROCESS_STATS_H_

#include "absl/status/statusor.h"

namespace fleetmem::observability {

struct ProcessStats {
  double cpu_seconds = 0;         // user + system
  double resident_bytes = 0;      // RSS
  double virtual_bytes = 0;       // address space
  double open_fds = 0;            // entries of /proc/self/fd
  double max_fds = 0;             // the soft RLIMIT_NOFILE
  double start_time_seconds = 0;  // since the Unix epoch
};

// Reads /proc/self/stat, /proc/stat (boot time), /proc/self/fd and the
// descriptor limit. UNAVAILABLE naming the file that cannot be read or
// parsed (e.g. no /proc).
absl::StatusOr<ProcessStats> ReadProcessStats();

// The C library's heap, over all malloc arenas (glibc's mallinfo2): what
// tells a leak (in_use grows) from memory malloc keeps after it was freed
// (free grows; RSS holds it until malloc trims or reuses it).
struct HeapStats {
  double in_use_bytes = 0;   // allocated blocks, mmapped ones included
  double free_bytes = 0;     // free blocks malloc holds in its arenas
  double mmapped_bytes = 0;  // blocks mmapped on their own (large ones)
};

// Zeros where the C library does not say (not glibc, or a sanitizer's
// allocator).
HeapStats ReadHeapStats();

// Gives the heap's free pages back to the system (glibc's malloc_trim(0),
// over every arena; the blocks stay malloc's, their pages stop being
// resident). A no-op elsewhere. Takes each arena's lock in turn: a few
// milliseconds at a heap of 100 MiB.
void TrimHeap();

}  // namespace fleetmem::observability

#endif  // FLEETMEM_SERVICES_OBSERVABILITY_PROCESS_STATS_H_
