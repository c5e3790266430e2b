#include "services/storage/wal_room.h"

#include <atomic>
#include <chrono>
#include <memory>
#include <string>
#include <thread>

#include "gtest/gtest.h"
#include "rocksdb/db.h"
#include "rocksdb/env.h"
#include "services/storage/testing/store_test_util.h"

namespace fleetmem::storage {
namespace {

using testing::TempDir;

// A filesystem whose write-ahead logs find the disk full while `full` is
// set: their Allocate (fallocate) says "no space", and an Append made then
// fails as it would on a full disk, which is what made Debian's RocksDB
// abort on its next use of that log's writer.
class FullDisk : public rocksdb::FileSystemWrapper {
 public:
  FullDisk() : FileSystemWrapper(rocksdb::FileSystem::Default()) {}
  const char* Name() const override { return "FullDisk"; }

  std::atomic<bool> full = false;
  std::atomic<int> refused_allocations = 0;
  std::atomic<int> failed_appends = 0;

  rocksdb::IOStatus NewWritableFile(
      const std::string& path, const rocksdb::FileOptions& options,
      std::unique_ptr<rocksdb::FSWritableFile>* result,
      rocksdb::IODebugContext* dbg) override {
    rocksdb::IOStatus opened =
        target()->NewWritableFile(path, options, result, dbg);
    if (opened.ok() && path.ends_with(".log")) {
      *result = std::make_unique<File>(std::move(*result), this);
    }
    return opened;
  }

 private:
  class File : public rocksdb::FSWritableFileOwnerWrapper {
   public:
    File(std::unique_ptr<rocksdb::FSWritableFile> file, FullDisk* disk)
        : FSWritableFileOwnerWrapper(std::move(file)), disk_(disk) {}
    rocksdb::IOStatus Allocate(uint64_t offset, uint64_t len,
                               const rocksdb::IOOptions& io,
                               rocksdb::IODebugContext* dbg) override {
      if (disk_->full) {
        ++disk_->refused_allocations;
        return rocksdb::IOStatus::NoSpace("no space left on device");
      }
      return target()->Allocate(offset, len, io, dbg);
    }
    rocksdb::IOStatus Append(const rocksdb::Slice& data,
                             const rocksdb::IOOptions& io,
                             rocksdb::IODebugContext* dbg) override {
      if (disk_->full) {
        ++disk_->failed_appends;
        return rocksdb::IOStatus::NoSpace("no space left on device");
      }
      return target()->Append(data, io, dbg);
    }
    rocksdb::IOStatus Append(const rocksdb::Slice& data,
                             const rocksdb::IOOptions& io,
                             const rocksdb::DataVerificationInfo&,
                             rocksdb::IODebugContext* dbg) override {
      return Append(data, io, dbg);
    }

   private:
    FullDisk* const disk_;
  };
};

// A write that meets a full disk gives back the reserve, then waits for
// space, and completes once there is some: RocksDB's log writer never sees
// the error, so the store goes on writing, closes and reopens.
TEST(WalRoomTest, AWriteMeetingAFullDiskWaitsForSpaceAndCompletes) {
  TempDir dir;
  auto disk = std::make_shared<FullDisk>();
  std::atomic<int> gave_back = 0;
  WalRoomOptions room;
  room.give_back = [&] {
    ++gave_back;
    return false;  // nothing to give: wait
  };
  room.poll = absl::Milliseconds(10);
  std::unique_ptr<rocksdb::Env> env =
      rocksdb::NewCompositeEnv(NewWalRoomFileSystem(room, disk));
  rocksdb::Options options;
  options.create_if_missing = true;
  options.env = env.get();
  rocksdb::DB* raw = nullptr;
  ASSERT_TRUE(rocksdb::DB::Open(options, dir.path() + "/db", &raw).ok());
  std::unique_ptr<rocksdb::DB> db(raw);
  rocksdb::WriteOptions sync;
  sync.sync = true;
  ASSERT_TRUE(db->Put(sync, "a", "1").ok());

  disk->full = true;
  std::atomic<bool> done = false;
  rocksdb::Status written;
  std::thread writer([&] {
    written = db->Put(sync, "b", std::string(1000, 'x'));
    done = true;
  });
  std::this_thread::sleep_for(std::chrono::milliseconds(300));
  EXPECT_FALSE(done.load()) << written.ToString();
  EXPECT_GT(disk->refused_allocations.load(), 1);
  EXPECT_EQ(gave_back.load(), 1);
  EXPECT_EQ(disk->failed_appends.load(), 0);
  disk->full = false;
  writer.join();
  EXPECT_TRUE(written.ok()) << written.ToString();
  ASSERT_TRUE(db->Put(sync, "c", "3").ok());
  ASSERT_TRUE(db->Close().ok());
  db.reset();

  ASSERT_TRUE(rocksdb::DB::Open(options, dir.path() + "/db", &raw).ok());
  db.reset(raw);
  for (const char* key : {"a", "b", "c"}) {
    std::string value;
    EXPECT_TRUE(db->Get(rocksdb::ReadOptions(), key, &value).ok()) << key;
  }
  EXPECT_TRUE(db->Close().ok());
}

// Where the base filesystem has no fallocate (or it fails otherwise), the
// append goes ahead as it would without the wrapper.
TEST(WalRoomTest, OtherAllocationErrorsLeaveTheAppendAlone) {
  TempDir dir;
  WalRoomOptions room;
  std::unique_ptr<rocksdb::Env> env =
      rocksdb::NewCompositeEnv(NewWalRoomFileSystem(room));
  rocksdb::Options options;
  options.create_if_missing = true;
  options.env = env.get();
  options.allow_fallocate = false;
  rocksdb::DB* raw = nullptr;
  ASSERT_TRUE(rocksdb::DB::Open(options, dir.path() + "/db", &raw).ok());
  std::unique_ptr<rocksdb::DB> db(raw);
  EXPECT_TRUE(db->Put(rocksdb::WriteOptions(), "a", "1").ok());
  EXPECT_TRUE(db->Close().ok());
}

}  // namespace
}  // namespace fleetmem::storage
