#include "services/storage/wal_room.h"

#include <string>
#include <string_view>
#include <utility>

#include "absl/time/clock.h"
#include "services/common/log.h"

namespace fleetmem::storage {
namespace {

// The files whose writer RocksDB reuses after a failed append: the
// write-ahead logs (NNNNNN.log; the info log is "LOG") and the manifests.
bool Guarded(const std::string& path) {
  const std::string_view name =
      std::string_view(path).substr(path.find_last_of('/') + 1);
  return name.ends_with(".log") || name.starts_with("MANIFEST-");
}

class RoomFile : public rocksdb::FSWritableFileOwnerWrapper {
 public:
  RoomFile(std::unique_ptr<rocksdb::FSWritableFile> file, std::string path,
           const WalRoomOptions* options)
      : FSWritableFileOwnerWrapper(std::move(file)),
        path_(std::move(path)),
        options_(options) {}

  rocksdb::IOStatus Append(const rocksdb::Slice& data,
                           const rocksdb::IOOptions& io,
                           rocksdb::IODebugContext* dbg) override {
    MakeRoom(data.size(), io, dbg);
    return target()->Append(data, io, dbg);
  }
  rocksdb::IOStatus Append(const rocksdb::Slice& data,
                           const rocksdb::IOOptions& io,
                           const rocksdb::DataVerificationInfo& info,
                           rocksdb::IODebugContext* dbg) override {
    MakeRoom(data.size(), io, dbg);
    return target()->Append(data, io, info, dbg);
  }

 private:
  // Reserves `bytes` at the end of the file, waiting for space if the disk
  // is full. Other errors (a filesystem without fallocate) leave the append
  // to meet whatever it meets, as without this wrapper.
  void MakeRoom(size_t bytes, const rocksdb::IOOptions& io,
                rocksdb::IODebugContext* dbg) {
    if (bytes == 0) return;
    const uint64_t at = target()->GetFileSize(io, dbg);
    bool gave_back = false;
    bool waited = false;
    while (true) {
      const rocksdb::IOStatus allocated =
          target()->Allocate(at, bytes, io, dbg);
      if (allocated.ok() || !allocated.IsNoSpace()) break;
      if (!gave_back) {
        gave_back = true;
        if (options_->give_back && options_->give_back()) continue;
      }
      if (!waited) {
        waited = true;
        FLEETMEM_LOG(kError)
            << "disk full under a RocksDB write of " << bytes << " bytes to "
            << path_ << " (another process filled it?): the write waits for "
            << "space, polling every " << options_->poll;
      }
      absl::SleepFor(options_->poll);
    }
    if (waited) {
      FLEETMEM_LOG(kInfo) << "space found for the RocksDB write to " << path_;
    }
  }

  const std::string path_;
  const WalRoomOptions* const options_;
};

class WalRoomFileSystem : public rocksdb::FileSystemWrapper {
 public:
  WalRoomFileSystem(WalRoomOptions options,
                    std::shared_ptr<rocksdb::FileSystem> base)
      : FileSystemWrapper(std::move(base)), options_(std::move(options)) {}

  const char* Name() const override { return "FleetmemWalRoomFileSystem"; }

  rocksdb::IOStatus NewWritableFile(
      const std::string& path, const rocksdb::FileOptions& file_options,
      std::unique_ptr<rocksdb::FSWritableFile>* result,
      rocksdb::IODebugContext* dbg) override {
    return Wrap(path,
                target()->NewWritableFile(path, file_options, result, dbg),
                result);
  }
  rocksdb::IOStatus ReopenWritableFile(
      const std::string& path, const rocksdb::FileOptions& file_options,
      std::unique_ptr<rocksdb::FSWritableFile>* result,
      rocksdb::IODebugContext* dbg) override {
    return Wrap(path,
                target()->ReopenWritableFile(path, file_options, result, dbg),
                result);
  }
  rocksdb::IOStatus ReuseWritableFile(
      const std::string& path, const std::string& old_path,
      const rocksdb::FileOptions& file_options,
      std::unique_ptr<rocksdb::FSWritableFile>* result,
      rocksdb::IODebugContext* dbg) override {
    return Wrap(
        path,
        target()->ReuseWritableFile(path, old_path, file_options, result, dbg),
        result);
  }

 private:
  rocksdb::IOStatus Wrap(const std::string& path, rocksdb::IOStatus opened,
                         std::unique_ptr<rocksdb::FSWritableFile>* result) {
    if (opened.ok() && Guarded(path)) {
      *result = std::make_unique<RoomFile>(std::move(*result), path, &options_);
    }
    return opened;
  }

  const WalRoomOptions options_;
};

}  // namespace

std::shared_ptr<rocksdb::FileSystem> NewWalRoomFileSystem(
    WalRoomOptions options, std::shared_ptr<rocksdb::FileSystem> base) {
  if (base == nullptr) base = rocksdb::FileSystem::Default();
  return std::make_shared<WalRoomFileSystem>(std::move(options),
                                             std::move(base));
}

}  // namespace fleetmem::storage
