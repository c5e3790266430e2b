// Index snapshots on disk (the file side of MemoryStore::SaveIndexSnapshot):
// one file per key (a fleet id) in a directory, named after the key's
// XXH3-64 in hex (a fixed length whatever the key), framed as
//   "FMIDXSN2" | stamp (uint64) | key (uint64 length, bytes) | payload |
//   the payload's self-checked ranges (offset, length: uint64 each) |
//   their count (uint64) | payload size (uint64) | XXH3-64 of everything
//   after the magic but those ranges (uint64)
// The self-checked ranges (ByteWriter::PutSelfCheckedBytes: an int8
// graph's floats, whose rows carry their own checks) are neither read nor
// checked when the file is: their reader checks what it reads. FMIDXSN1
// files (no ranges; the checksum covers everything) are still read.
// and written atomically (a temporary file, fsync, rename, fsync of the
// directory), so a crash leaves the earlier file or the new one, whole. The
// stamp records the state of the store that wrote it (RocksDB's latest
// sequence number); readers reconcile a snapshot with the store instead of
// requiring the stamp to be current.
#ifndef FLEETMEM_SERVICES_STORAGE_SNAPSHOT_FILE_H_
#define FLEETMEM_SERVICES_STORAGE_SNAPSHOT_FILE_H_

#include <cstdint>
#include <functional>
#include <span>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "services/core/byte_stream.h"
#include "services/engine/memory_store.h"

namespace fleetmem::storage {

// Writes the payload `write` produces as the snapshot of `key` in
// `directory` (which must exist), replacing the one there. `check_room`,
// if set, is asked before each 1 MiB written and stops the write with its
// error (a disk reserve). `written`, if set, is called once `write` has
// returned OK and its bytes are in the file (not yet synced): the caller
// may change what `write` read from then on; it gets the file's checksum
// (SnapshotFileId::digest). `write`'s ByteWriter says where the payload
// lies in the file (ByteWriter::file): what it wrote may be read from
// there once this returns OK. On any error (`write`'s,
// `check_room`'s, or I/O: a full disk, a failed fsync) the earlier snapshot
// of `key`, if any, is left as it was, no temporary file remains, and the
// status says so. Calls for one key must not overlap (they share the
// temporary file).
absl::Status WriteSnapshotFile(
    const std::string& directory, std::string_view key, uint64_t stamp,
    const std::function<absl::Status(core::ByteWriter&)>& write,
    const std::function<absl::Status()>& check_room = nullptr,
    const std::function<void(uint64_t digest)>& written = nullptr);

// What tells one snapshot file from another: the stamp it was written with
// and the checksum in its trailer.
struct SnapshotFileId {
  uint64_t stamp = 0;
  uint64_t digest = 0;
  friend bool operator==(const SnapshotFileId&,
                         const SnapshotFileId&) = default;
};

// The id of `key`'s snapshot in `directory`, read off its frame without
// checking the payload (ReadSnapshotFile does): NOT_FOUND when there is
// none, DATA_LOSS when its frame is damaged or it is another key's.
absl::StatusOr<SnapshotFileId> ReadSnapshotFileId(const std::string& directory,
                                                  std::string_view key);

// Calls `read` with the payload of `key`'s snapshot in `directory`, mapped
// from the file (`file` says where it lies there; `read` may keep the file
// open), once the frame is intact and the key is `key`, and before the
// checksum is checked (the pages it covers are read in first; the
// self-checked ranges' are not): `check` checks it on the caller's thread (it
// is valid until `read` returns). Returns `read`'s status once `check`, called
// by `read` or after it, passed; the file stays. NOT_FOUND when there is
// none, DATA_LOSS when it is damaged (its frame, and `read` is not called;
// or its checksum): the file is then removed. `*stamp`, if given, gets the
// stamp the file was written with.
absl::Status ReadSnapshotFile(const std::string& directory,
                              std::string_view key,
                              const engine::IndexSnapshotRead& read,
                              uint64_t* stamp = nullptr);

// The file that holds `key`'s snapshot in `directory`.
std::string SnapshotFilePath(const std::string& directory,
                             std::string_view key);

}  // namespace fleetmem::storage

#endif  // FLEETMEM_SERVICES_STORAGE_SNAPSHOT_FILE_H_
