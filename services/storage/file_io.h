// POSIX file plumbing shared by the store's own files (snapshot_file.h,
// segment_log.h): errno as a status, and directory syncs.
#ifndef FLEETMEM_SERVICES_STORAGE_FILE_IO_H_
#define FLEETMEM_SERVICES_STORAGE_FILE_IO_H_

#include <string>
#include <string_view>

#include "absl/status/status.h"

namespace fleetmem::storage::file_io {

// strerror(error).
std::string ErrnoText(int error);

// `what`: strerror(error). ENOSPC and EDQUOT are a full disk
// (RESOURCE_EXHAUSTED, as the store's reserve says it), anything else
// UNAVAILABLE.
absl::Status IoError(int error, std::string_view what);

// fsync of `directory` itself (names created, renamed or removed in it
// become durable). IoError on failure.
absl::Status SyncDirectory(const std::string& directory);

}  // namespace fleetmem::storage::file_io

#endif  // FLEETMEM_SERVICES_STORAGE_FILE_IO_H_
