// Marks the calling thread as background work: a name that `top -H`,
// `ps -L` and gdb show, and a nice value above the calls' (Linux keeps one
// per thread, and threads it starts inherit it). The write path's appliers
// and the tiered index's graph builder call it, so that when a burst keeps
// both cores busy the scheduler gives the threads answering calls (uploads'
// acknowledgements, queries) the larger share and the backlog absorbs the
// rest (docs/performance.md, "The write path").
#ifndef FLEETMEM_SERVICES_COMMON_BACKGROUND_THREAD_H_
#define FLEETMEM_SERVICES_COMMON_BACKGROUND_THREAD_H_

#include <string_view>

#include "absl/status/status.h"

namespace fleetmem::common {

// Names the calling thread `name` (at most its first 15 characters) and
// sets its nice value to `nice` (0..19) where that is lower priority than
// it has (never higher: a thread started by a background thread already
// has its nice value, a server started with `nice -n 15` keeps 15).
// Lowering its own priority needs no privilege. INTERNAL with the system's
// reason if a call fails (the thread then runs as before).
absl::Status MarkBackgroundThread(std::string_view name, int nice);

}  // namespace fleetmem::common

#endif  // FLEETMEM_SERVICES_COMMON_BACKGROUND_THREAD_H_
