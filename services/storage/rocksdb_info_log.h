// RocksDB's info log, sent to the server's log instead of a LOG file in the
// data directory.
//
// Why: Debian's RocksDB (7.8.3) writes its info log through a file writer
// that asserts when used again after a failed write (the
// "sync_without_flush_called_" assertion, as in wal_room.h). With the disk
// full, RocksDB logs the background error it met to that file, the write
// fails, and its next line aborted the server (the disk-full test under
// the sanitizer build, CI of 2026-11-29). Kept off the disk, the info log
// cannot fail; and an operator finds RocksDB's warnings and errors where
// the server's own are, on stderr.
//
// RocksDB's warnings and errors are logged at the server's warning and
// error levels; its info, header and debug lines are not kept (never
// formatted): they are RocksDB's own diagnostics — the options dump alone is
// about 1,250 lines at each open — and at the server's debug level they
// buried what a failing test or an operator looks for.
#ifndef FLEETMEM_SERVICES_STORAGE_ROCKSDB_INFO_LOG_H_
#define FLEETMEM_SERVICES_STORAGE_ROCKSDB_INFO_LOG_H_

#include <memory>

#include "rocksdb/env.h"

namespace fleetmem::storage {

// For rocksdb::Options::info_log.
std::shared_ptr<rocksdb::Logger> NewRocksDbInfoLog();

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_ROCKSDB_INFO_LOG_H_
