// A RocksDB FileSystem over the default one whose write-ahead-log and
// manifest appends never meet a full disk.
//
// Why: Debian's RocksDB (7.8.3) asserts when a file writer that has failed
// a write is used again (WritableFileWriter's "sync_without_flush_called_"
// assertion), and after a write-ahead-log append fails it uses that
// writer again: on the next write, on Resume, and at Close
// (facebook/rocksdb#12448, fixed in 9.1). Another process filling the disk
// between the store's free-space check and RocksDB's append aborted the
// server (3 of 30 trials in the third outside sweep). Here every such
// append first reserves its bytes (fallocate, keeping the size); when the
// disk is full it calls `give_back` (the store's reserve file goes) and
// tries again, and if there is still no room it waits for space, polling,
// instead of failing: RocksDB's writer never sees the error. Writes from
// the store are refused long before (storage.min_free_bytes), so only a
// write already under way can wait here.
#ifndef FLEETMEM_SERVICES_STORAGE_WAL_ROOM_H_
#define FLEETMEM_SERVICES_STORAGE_WAL_ROOM_H_

#include <functional>
#include <memory>

#include "absl/time/time.h"
#include "rocksdb/file_system.h"

namespace fleetmem::storage {

struct WalRoomOptions {
  // Frees space for a waiting append (the store's reserve file); true if it
  // freed any. May be empty.
  std::function<bool()> give_back;
  // How often an append that found no room tries again.
  absl::Duration poll = absl::Milliseconds(100);
};

// Wraps `base` (rocksdb::FileSystem::Default() when null).
std::shared_ptr<rocksdb::FileSystem> NewWalRoomFileSystem(
    WalRoomOptions options,
    std::shared_ptr<rocksdb::FileSystem> base = nullptr);

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_WAL_ROOM_H_
