#include "services/storage/segment_log.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/resource.h>
#include <unistd.h>

#include <atomic>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <variant>
#include <vector>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "rocksdb/db.h"
#include "services/storage/keys.h"
#include "services/storage/record_codec.h"
#include "services/storage/rocksdb_store.h"
#include "services/storage/testing/store_test_util.h"

namespace fleetmem::storage {
namespace {

using ::testing::HasSubstr;
using testing::MakeTrace;
using testing::TempDir;

// Entry `sequence` holds `size` traces of robot "r" from seq 10 * sequence.
std::vector<core::MemoryTrace> EntryTraces(uint64_t sequence, int size = 3) {
  std::vector<core::MemoryTrace> traces;
  for (int i = 0; i < size; ++i) {
    traces.push_back(MakeTrace("r", sequence * 10 + i));
  }
  return traces;
}

// Appends entries first..last (the log gives the sequences after its last
// and after first - 1: these, unless its last is later, an error then).
absl::Status AppendEntries(SegmentLog& log, const std::string& fleet,
                           uint64_t first, uint64_t last) {
  std::vector<std::vector<core::MemoryTrace>> held;
  std::vector<engine::LogAppend> appends;
  for (uint64_t s = first; s <= last; ++s) held.push_back(EntryTraces(s));
  for (uint64_t s = first; s <= last; ++s) {
    appends.push_back({engine::UploadRecord{held[s - first]}});
  }
  absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
      log.Append(fleet, appends, {.above = first - 1});
  if (!appended.ok()) return appended.status();
  for (uint64_t s = first; s <= last; ++s) {
    if ((*appended)[s - first].sequence != s) {
      return absl::InternalError(absl::StrCat("entry ", s, " got sequence ",
                                              (*appended)[s - first].sequence));
    }
  }
  return absl::OkStatus();
}

// Each fleet with entries and its last sequence, sorted by fleet.
std::vector<std::pair<std::string, uint64_t>> Tails(SegmentLog& log) {
  std::vector<std::pair<std::string, uint64_t>> tails;
  const std::vector<std::string> fleets = log.Fleets().value();
  for (const std::string& fleet : fleets) {
    tails.emplace_back(fleet, log.Bounds(fleet)->last);
  }
  return tails;
}

// The sequences Read gives after `after`, in pages of 4; each entry's
// traces checked.
std::vector<uint64_t> ReadAll(SegmentLog& log, const std::string& fleet,
                              uint64_t after = 0) {
  std::vector<uint64_t> sequences;
  while (true) {
    absl::StatusOr<std::vector<engine::LogEntry>> page =
        log.Read(fleet, after, 4);
    EXPECT_TRUE(page.ok()) << page.status();
    if (!page.ok() || page->empty()) break;
    for (const engine::LogEntry& entry : *page) {
      const std::vector<core::MemoryTrace> expected =
          EntryTraces(entry.sequence);
      const std::span<const core::MemoryTrace> traces = entry.traces();
      EXPECT_EQ(traces.size(), expected.size());
      for (size_t i = 0; i < expected.size() && i < traces.size(); ++i) {
        EXPECT_EQ(traces[i].seq, expected[i].seq);
        EXPECT_EQ(traces[i].code, expected[i].code);
      }
      sequences.push_back(entry.sequence);
      after = entry.sequence;
    }
  }
  return sequences;
}

std::vector<uint64_t> Range(uint64_t first, uint64_t last) {
  std::vector<uint64_t> out;
  for (uint64_t s = first; s <= last; ++s) out.push_back(s);
  return out;
}

std::unique_ptr<SegmentLog> OpenLog(const std::string& directory,
                                    uint64_t segment_bytes = 1000) {
  SegmentLogOptions options;
  options.directory = directory;
  options.segment_bytes = segment_bytes;  // a few entries per segment
  options.spare_segments = 2;
  absl::StatusOr<std::unique_ptr<SegmentLog>> log =
      SegmentLog::Open(std::move(options));
  EXPECT_TRUE(log.ok()) << log.status();
  return log.ok() ? std::move(*log) : nullptr;
}

size_t CountFiles(const std::string& directory, std::string_view prefix) {
  size_t count = 0;
  for (const auto& entry : std::filesystem::directory_iterator(directory)) {
    if (entry.path().filename().string().starts_with(prefix)) ++count;
  }
  return count;
}

TEST(SegmentLogTest, EntriesReadBackAcrossSegmentsTrimsAndReopens) {
  TempDir dir;
  const std::string path = dir.path() + "/log";
  {
    std::unique_ptr<SegmentLog> log = OpenLog(path);
    ASSERT_NE(log, nullptr);
    for (uint64_t s = 1; s <= 30; s += 3) {
      ASSERT_TRUE(AppendEntries(*log, "fleet-a", s, s + 2).ok());
    }
    ASSERT_TRUE(AppendEntries(*log, "b", 1, 2).ok());
    EXPECT_EQ(ReadAll(*log, "fleet-a"), Range(1, 30));
    const uint64_t bytes = log->Bytes();
    EXPECT_GT(bytes, 32u * 32);  // 32 entries of 3 traces
    EXPECT_EQ(ReadAll(*log, "fleet-a", 17), Range(18, 30));
    EXPECT_EQ(ReadAll(*log, "nobody"), std::vector<uint64_t>());
    EXPECT_EQ(Tails(*log), (std::vector<std::pair<std::string, uint64_t>>{
                               {"b", 2}, {"fleet-a", 30}}));
    EXPECT_GT(CountFiles(path + "/f-fleet-a", "0"), 3u);
    ASSERT_TRUE(log->Trim("fleet-a", 20).ok());
    // Whole segments at or below 20 are gone, kept for reuse up to 2.
    EXPECT_EQ(CountFiles(path + "/f-fleet-a", "spare-"), 2u);
    EXPECT_EQ(ReadAll(*log, "fleet-a", 20), Range(21, 30));
    EXPECT_LT(log->Bytes(), bytes);
  }
  std::unique_ptr<SegmentLog> log = OpenLog(path);
  ASSERT_NE(log, nullptr);
  std::vector<uint64_t> kept = ReadAll(*log, "fleet-a");
  ASSERT_FALSE(kept.empty());
  EXPECT_LE(kept.front(), 21u);
  EXPECT_EQ(kept.back(), 30u);
  EXPECT_EQ(ReadAll(*log, "fleet-a", 20), Range(21, 30));
  EXPECT_EQ(ReadAll(*log, "b"), Range(1, 2));
  // Appends go on after a reopen, into reused segments: nothing of what
  // those files held before is read back.
  for (uint64_t s = 31; s <= 60; s += 3) {
    ASSERT_TRUE(AppendEntries(*log, "fleet-a", s, s + 2).ok());
  }
  ASSERT_TRUE(log->Trim("fleet-a", 45).ok());
  EXPECT_EQ(ReadAll(*log, "fleet-a", 45), Range(46, 60));
  // A short disk: the spares go, and appends go on without them.
  const uint64_t spare = log->SpareBytes();
  EXPECT_GT(spare, 0u);
  EXPECT_EQ(log->DropSpares(), spare);
  EXPECT_EQ(CountFiles(path + "/f-fleet-a", "spare-"), 0u);
  EXPECT_EQ(log->SpareBytes(), 0u);
  ASSERT_TRUE(AppendEntries(*log, "fleet-a", 61, 66).ok());
  ASSERT_TRUE(log->Trim("fleet-a", 45).ok());
  EXPECT_EQ(ReadAll(*log, "fleet-a", 45), Range(46, 66));
  log = OpenLog(path);
  ASSERT_NE(log, nullptr);
  EXPECT_EQ(ReadAll(*log, "fleet-a", 45), Range(46, 66));
  EXPECT_EQ(Tails(*log).back(),
            std::make_pair(std::string("fleet-a"), uint64_t{66}));
}

// Appends entries 1..2, then 3 (its own append), and returns the segment
// and where entry 3 begins in it.
std::pair<std::string, uintmax_t> TwoAppends(const std::string& path,
                                             std::unique_ptr<SegmentLog>& log) {
  log = OpenLog(path, 1 << 20);
  EXPECT_NE(log, nullptr);
  EXPECT_TRUE(AppendEntries(*log, "f", 1, 2).ok());
  const std::string segment =
      std::filesystem::directory_iterator(path + "/f-f")->path();
  const uintmax_t third = std::filesystem::file_size(segment);
  EXPECT_TRUE(AppendEntries(*log, "f", 3, 3).ok());
  return {segment, third};
}

// A backlog of many segments holds one descriptor (the segment appends go
// to), not one per segment: many fleets' bursts must not exhaust the
// process's files.
// The log gives the sequences: after its last (kept when every entry is
// trimmed, and across a reopen) and after the writer's floor. Calls are
// entries like uploads; `only_first` appends to an empty log only.
TEST(SegmentLogTest, TheLogGivesSequencesAndKeepsEveryKindOfRecord) {
  TempDir dir;
  const std::string path = dir.path() + "/log";
  const std::vector<core::MemoryTrace> traces = EntryTraces(1);
  const std::vector<engine::LogAppend> appends = {
      {engine::UploadRecord{traces}},
      {engine::ConsolidateRecord{}},
      {engine::SampleReplayRecord{"r", 4, "req-9"}}};
  {
    std::unique_ptr<SegmentLog> log = OpenLog(path);
    ASSERT_NE(log, nullptr);
    EXPECT_EQ(log->Bounds("f")->last, 0u);
    absl::StatusOr<std::vector<engine::AppendedEntry>> appended =
        log->Append("f", appends, {.only_first = true});
    ASSERT_TRUE(appended.ok()) << appended.status();
    EXPECT_EQ(appended->back().sequence, 3u);
    EXPECT_EQ(log->Append("f", appends, {.only_first = true}).status().code(),
              absl::StatusCode::kFailedPrecondition);
    appended = log->Append("f", {&appends[1], 1}, {.above = 10});
    ASSERT_TRUE(appended.ok()) << appended.status();
    EXPECT_EQ(appended->front().sequence, 11u);
    absl::StatusOr<std::vector<engine::LogEntry>> read = log->Read("f", 0, 10);
    ASSERT_TRUE(read.ok()) << read.status();
    ASSERT_EQ(read->size(), 4u);
    EXPECT_EQ((*read)[0].traces().size(), 3u);
    EXPECT_TRUE(
        std::holds_alternative<engine::ConsolidateRecord>((*read)[1].record));
    const auto* call =
        std::get_if<engine::SampleReplayCall>(&(*read)[2].record);
    ASSERT_NE(call, nullptr);
    EXPECT_EQ(call->robot_id, "r");
    EXPECT_EQ(call->count, 4u);
    EXPECT_EQ(call->request_id, "req-9");
    EXPECT_EQ((*read)[3].sequence, 11u);
    // Every entry applied: the segment appends go to stays.
    ASSERT_TRUE(log->Trim("f", 11).ok());
  }
  std::unique_ptr<SegmentLog> log = OpenLog(path);
  ASSERT_NE(log, nullptr);
  EXPECT_EQ(log->Bounds("f")->last, 11u);
  absl::StatusOr<std::vector<engine::LogEntry>> read = log->Read("f", 0, 10);
  ASSERT_TRUE(read.ok()) << read.status();
  ASSERT_EQ(read->size(), 1u);
  EXPECT_EQ(read->front().sequence, 11u);
  absl::StatusOr<std::vector<engine::AppendedEntry>> next =
      log->Append("f", {&appends[0], 1}, {});
  ASSERT_TRUE(next.ok()) << next.status();
  EXPECT_EQ(next->front().sequence, 12u);
}

TEST(SegmentLogTest, ABacklogOfManySegmentsHoldsOneDescriptor) {
  TempDir dir;
  auto open_files = [] {
    return std::distance(std::filesystem::directory_iterator("/proc/self/fd"),
                         std::filesystem::directory_iterator());
  };
  const auto before = open_files();
  std::unique_ptr<SegmentLog> log = OpenLog(dir.path() + "/log", 1000);
  ASSERT_NE(log, nullptr);
  for (uint64_t s = 1; s <= 120; s += 3) {
    ASSERT_TRUE(AppendEntries(*log, "f", s, s + 2).ok());
  }
  EXPECT_GT(CountFiles(dir.path() + "/log/f-f", "0"), 30u);
  EXPECT_LE(open_files(), before + 1);
  EXPECT_EQ(ReadAll(*log, "f"), Range(1, 120));
  EXPECT_LE(open_files(), before + 1);
}

// The log at `path` holds entries 1..2 of fleet "f" and nothing after them;
// appends go on with 3, and a reopen reads 1..4.
void ExpectEntries1And2ThenAppendsGoOn(const std::string& path,
                                       std::unique_ptr<SegmentLog>& log) {
  EXPECT_EQ(ReadAll(*log, "f"), Range(1, 2));
  EXPECT_EQ(Tails(*log).front().second, 2u);
  ASSERT_TRUE(AppendEntries(*log, "f", 3, 4).ok());
  EXPECT_EQ(ReadAll(*log, "f"), Range(1, 4));
  log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  EXPECT_EQ(ReadAll(*log, "f"), Range(1, 4));
  EXPECT_TRUE(log->Losses("f").empty());
}

TEST(SegmentLogTest, ATornTailIsCutAtReopenAndAppendsGoOnAfterIt) {
  TempDir dir;
  const std::string path = dir.path() + "/log";
  std::unique_ptr<SegmentLog> log;
  const auto [segment, third] = TwoAppends(path, log);
  log.reset();
  // A crash in the middle of entry 3's write.
  std::filesystem::resize_file(segment, third + 40);
  log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  EXPECT_TRUE(log->Losses("f").empty());  // never acknowledged
  ExpectEntries1And2ThenAppendsGoOn(path, log);
}

// After a reopen the first append starts a segment (the last one may end
// in a torn write) and the appends after it go on in that segment, not one
// segment each.
TEST(SegmentLogTest, AfterAReopenAppendsShareOneNewSegment) {
  TempDir dir;
  const std::string path = dir.path() + "/log";
  std::unique_ptr<SegmentLog> log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  ASSERT_TRUE(AppendEntries(*log, "f", 1, 2).ok());
  log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  for (uint64_t s = 3; s <= 6; ++s) {
    ASSERT_TRUE(AppendEntries(*log, "f", s, s).ok());
  }
  EXPECT_EQ(CountFiles(path + "/f-f", "0"), 2u);  // the first and one more
  EXPECT_EQ(ReadAll(*log, "f"), Range(1, 6));
  log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  EXPECT_EQ(ReadAll(*log, "f"), Range(1, 6));
}

// Flips one bit of the byte at `at` of `file`.
void FlipByte(const std::string& file, uint64_t at) {
  const int fd = ::open(file.c_str(), O_RDWR);
  ASSERT_GE(fd, 0);
  char byte = 0;
  ASSERT_EQ(::pread(fd, &byte, 1, static_cast<off_t>(at)), 1);
  byte = static_cast<char>(byte ^ 0x40);
  ASSERT_EQ(::pwrite(fd, &byte, 1, static_cast<off_t>(at)), 1);
  ::close(fd);
}

// Where each entry's record lies in a segment file: [offset, end) by
// sequence (padding records left out), from the record headers.
std::map<uint64_t, std::pair<uint64_t, uint64_t>> EntryRecords(
    const std::string& file) {
  std::ifstream in(file, std::ios::binary);
  const std::string data((std::istreambuf_iterator<char>(in)),
                         std::istreambuf_iterator<char>());
  std::map<uint64_t, std::pair<uint64_t, uint64_t>> records;
  uint64_t at = 0;
  while (at + 32 <= data.size() && data.compare(at, 4, "FMLG") == 0) {
    uint64_t sequence = 0;
    uint32_t payload = 0;
    std::memcpy(&sequence, data.data() + at + 20, 8);
    std::memcpy(&payload, data.data() + at + 28, 4);
    if (sequence != 0) records[sequence] = {at, at + 32 + payload};
    at += 32 + payload;
  }
  return records;
}

std::vector<uint64_t> Without(std::vector<uint64_t> all,
                              const std::set<uint64_t>& lost) {
  std::erase_if(all, [&](uint64_t s) { return lost.contains(s); });
  return all;
}

std::set<uint64_t> LostSequences(SegmentLog& log, const std::string& fleet) {
  std::set<uint64_t> lost;
  for (const engine::LostLogEntries& range : log.Losses(fleet)) {
    for (uint64_t s = range.first; s <= range.last; ++s) lost.insert(s);
  }
  return lost;
}

// A damaged record in the middle of a segment (the outside sweep: one
// flipped byte lost every entry after it, silently): only it is lost,
// reported with its sequence, and the entries after it are read.
TEST(SegmentLogTest, ADamagedEntryIsLostAloneAndReported) {
  TempDir dir;
  const std::string path = dir.path() + "/log";
  std::unique_ptr<SegmentLog> log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  for (uint64_t s = 1; s <= 9; s += 3) {
    ASSERT_TRUE(AppendEntries(*log, "f", s, s + 2).ok());
  }
  const std::string segment =
      std::filesystem::directory_iterator(path + "/f-f")->path();
  const auto records = EntryRecords(segment);
  ASSERT_EQ(records.size(), 9u);
  // Entry 5, in the middle of the second append, damaged while the log is
  // open: Read passes over it and reports it once.
  FlipByte(segment, records.at(5).first + 40);
  EXPECT_EQ(ReadAll(*log, "f"), Without(Range(1, 9), {5}));
  EXPECT_EQ(LostSequences(*log, "f"), (std::set<uint64_t>{5}));
  EXPECT_EQ(ReadAll(*log, "f"), Without(Range(1, 9), {5}));
  EXPECT_EQ(log->Losses("f").size(), 1u);
  // After a restart: found at Open, the same.
  log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  EXPECT_EQ(ReadAll(*log, "f"), Without(Range(1, 9), {5}));
  ASSERT_EQ(log->Losses("f").size(), 1u);
  EXPECT_EQ(log->Losses("f")[0].first, 5u);
  EXPECT_EQ(log->Losses("f")[0].last, 5u);
  EXPECT_THAT(log->Losses("f")[0].detail, HasSubstr("is damaged at byte"));
  EXPECT_EQ(Tails(*log).front().second, 9u);
  // Its header damaged too (the length field: the reader cannot step over
  // it), and the last entry of the first append: both found alone.
  FlipByte(segment, records.at(5).first + 29);
  FlipByte(segment, records.at(3).first + 100);
  log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  EXPECT_EQ(ReadAll(*log, "f"), Without(Range(1, 9), {3, 5}));
  EXPECT_EQ(LostSequences(*log, "f"), (std::set<uint64_t>{3, 5}));
  // Appends go on after them.
  ASSERT_TRUE(AppendEntries(*log, "f", 10, 10).ok());
  EXPECT_EQ(ReadAll(*log, "f"), Without(Range(1, 10), {3, 5}));
}

// One byte flipped at a random place of a log of several segments, 200
// trials: what is lost is the entry whose record holds the byte (none for
// a padding record) and it is reported, the newest segment's last record
// included (the padding record that ends every append shows its write
// was whole).
TEST(SegmentLogTest, OneFlippedByteLosesAtMostTheEntryItIsIn) {
  TempDir dir;
  const std::string pristine = dir.path() + "/pristine";
  {
    std::unique_ptr<SegmentLog> log = OpenLog(pristine, 3000);
    ASSERT_NE(log, nullptr);
    for (uint64_t s = 1; s <= 40; s += 4) {
      ASSERT_TRUE(AppendEntries(*log, "f", s, s + 3).ok());
    }
  }
  std::vector<std::string> segments;
  for (const auto& entry :
       std::filesystem::directory_iterator(pristine + "/f-f")) {
    segments.push_back(entry.path().filename().string());
  }
  std::sort(segments.begin(), segments.end());
  ASSERT_GE(segments.size(), 3u);
  std::mt19937_64 rng(44);
  int reported = 0;
  for (int trial = 0; trial < 200; ++trial) {
    SCOPED_TRACE(absl::StrCat("trial ", trial));
    const std::string path = absl::StrCat(dir.path(), "/t", trial);
    std::filesystem::copy(pristine, path,
                          std::filesystem::copy_options::recursive);
    const std::string& name = segments[rng() % segments.size()];
    const std::string file = path + "/f-f/" + name;
    const auto records = EntryRecords(file);
    const uint64_t at = rng() % std::filesystem::file_size(file);
    FlipByte(file, at);
    std::optional<uint64_t> hit;
    for (const auto& [sequence, span] : records) {
      if (at >= span.first && at < span.second) hit = sequence;
    }
    std::unique_ptr<SegmentLog> log = OpenLog(path, 3000);
    ASSERT_NE(log, nullptr);
    const std::set<uint64_t> lost = LostSequences(*log, "f");
    if (!hit.has_value()) {
      EXPECT_TRUE(lost.empty());
      EXPECT_EQ(ReadAll(*log, "f"), Range(1, 40));
    } else {
      EXPECT_EQ(lost, (std::set<uint64_t>{*hit}));
      EXPECT_EQ(log->Losses("f").size(), 1u);  // reported once
      EXPECT_EQ(ReadAll(*log, "f"), Without(Range(1, 40), {*hit}));
      ++reported;
    }
    log.reset();
    std::filesystem::remove_all(path);
  }
  // Most bytes of a segment written with O_DIRECT are padding to 4 KiB.
  EXPECT_GT(reported, 40);
}

TEST(SegmentLogTest, ARefusedAppendStoresNothing) {
  TempDir dir;
  SegmentLogOptions options;
  options.directory = dir.path() + "/log";
  bool full = false;
  options.check_room = [&](std::string_view, uint64_t) {
    return full ? absl::ResourceExhaustedError("disk nearly full")
                : absl::OkStatus();
  };
  absl::StatusOr<std::unique_ptr<SegmentLog>> log =
      SegmentLog::Open(std::move(options));
  ASSERT_TRUE(log.ok()) << log.status();
  ASSERT_TRUE(AppendEntries(**log, "f", 1, 1).ok());
  full = true;
  EXPECT_EQ(AppendEntries(**log, "f", 2, 2).code(),
            absl::StatusCode::kResourceExhausted);
  full = false;
  EXPECT_EQ(ReadAll(**log, "f"), Range(1, 1));
  ASSERT_TRUE(AppendEntries(**log, "f", 2, 2).ok());
  EXPECT_EQ(ReadAll(**log, "f"), Range(1, 2));
}

// A write that fails half-way (here: past RLIMIT_FSIZE, as a full disk
// would) stores nothing of the append, now or after a restart, and the
// next append goes on in a new segment.
TEST(SegmentLogTest, AFailedWriteStoresNothingOfItsAppend) {
  TempDir dir;
  const std::string path = dir.path() + "/log";
  std::unique_ptr<SegmentLog> log = OpenLog(path, 1 << 20);
  ASSERT_NE(log, nullptr);
  ASSERT_TRUE(AppendEntries(*log, "f", 1, 2).ok());
  const std::string segment =
      std::filesystem::directory_iterator(path + "/f-f")->path();
  const uintmax_t size = std::filesystem::file_size(segment);
  struct sigaction ignore = {}, previous = {};
  ignore.sa_handler = SIG_IGN;
  ASSERT_EQ(::sigaction(SIGXFSZ, &ignore, &previous), 0);
  struct rlimit limit = {}, before = {};
  ASSERT_EQ(::getrlimit(RLIMIT_FSIZE, &before), 0);
  limit = before;
  limit.rlim_cur = size + 4096;  // entries 3..200 do not fit
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &limit), 0);
  const absl::Status failed = AppendEntries(*log, "f", 3, 200);
  ASSERT_EQ(::setrlimit(RLIMIT_FSIZE, &before), 0);
  ASSERT_EQ(::sigaction(SIGXFSZ, &previous, nullptr), 0);
  EXPECT_FALSE(failed.ok());
  EXPECT_THAT(failed.message(), HasSubstr("nothing of it was stored"));
  ExpectEntries1And2ThenAppendsGoOn(path, log);
}

// Trim makes the store's applies durable (before_trim) before any segment
// goes, and removes nothing if it cannot.
TEST(SegmentLogTest, TrimRemovesNothingUntilTheAppliedStateIsDurable) {
  TempDir dir;
  SegmentLogOptions options;
  options.directory = dir.path() + "/log";
  options.segment_bytes = 1000;
  int calls = 0;
  absl::Status durable = absl::UnavailableError("fsync failed");
  options.before_trim = [&] {
    ++calls;
    return durable;
  };
  absl::StatusOr<std::unique_ptr<SegmentLog>> log =
      SegmentLog::Open(std::move(options));
  ASSERT_TRUE(log.ok()) << log.status();
  for (uint64_t s = 1; s <= 12; s += 3) {
    ASSERT_TRUE(AppendEntries(**log, "f", s, s + 2).ok());
  }
  EXPECT_EQ((*log)->Trim("f", 12).code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(ReadAll(**log, "f"), Range(1, 12));
  durable = absl::OkStatus();
  ASSERT_TRUE((*log)->Trim("f", 12).ok());
  EXPECT_EQ(calls, 2);
  EXPECT_EQ(ReadAll(**log, "f", 12), std::vector<uint64_t>());
  EXPECT_LT(ReadAll(**log, "f").size(), 12u);
  // Nothing more to remove: not called.
  ASSERT_TRUE((*log)->Trim("f", 12).ok());
  EXPECT_EQ(calls, 2);
}

TEST(SegmentLogTest, ACopyHoldsEveryEntryAndNoTrimRunsBesideIt) {
  TempDir dir;
  std::unique_ptr<SegmentLog> log = OpenLog(dir.path() + "/log");
  ASSERT_NE(log, nullptr);
  ASSERT_TRUE(AppendEntries(*log, "f", 1, 12).ok());
  ASSERT_TRUE(AppendEntries(*log, "g", 1, 2).ok());
  bool first_ran = false;
  ASSERT_TRUE(log->CopyTo(dir.path() + "/copy",
                          [&] {
                            first_ran = true;
                            return absl::OkStatus();
                          })
                  .ok());
  EXPECT_TRUE(first_ran);
  std::unique_ptr<SegmentLog> copy = OpenLog(dir.path() + "/copy");
  ASSERT_NE(copy, nullptr);
  EXPECT_EQ(ReadAll(*copy, "f"), Range(1, 12));
  EXPECT_EQ(ReadAll(*copy, "g"), Range(1, 2));
  // A failing first step copies nothing.
  EXPECT_FALSE(log->CopyTo(dir.path() + "/copy2",
                           [] { return absl::UnavailableError("no"); })
                   .ok());
  EXPECT_FALSE(std::filesystem::exists(dir.path() + "/copy2"));
}

// The write path's use: one thread appends while another reads what is
// appended and trims what it has read (make test-tsan runs this).
TEST(SegmentLogTest, ReadsAndTrimsRunBesideAppends) {
  TempDir dir;
  std::unique_ptr<SegmentLog> log = OpenLog(dir.path() + "/log", 4000);
  ASSERT_NE(log, nullptr);
  constexpr uint64_t kEntries = 300;
  std::atomic<uint64_t> appended{0};
  std::thread writer([&] {
    for (uint64_t s = 1; s <= kEntries; ++s) {
      ASSERT_TRUE(AppendEntries(*log, "f", s, s).ok());
      appended = s;
    }
  });
  uint64_t applied = 0;
  bool failed = false;
  while (applied < kEntries && !failed) {
    absl::StatusOr<std::vector<engine::LogEntry>> page =
        log->Read("f", applied, 16);
    failed = !page.ok();
    EXPECT_TRUE(page.ok()) << page.status();
    for (size_t i = 0; page.ok() && i < page->size(); ++i) {
      const engine::LogEntry& entry = (*page)[i];
      failed |= entry.sequence != applied + 1 || entry.traces().size() != 3;
      EXPECT_EQ(entry.sequence, applied + 1);
      applied = entry.sequence;
    }
    // Entry `appended` + 1 may be readable before its Append returns.
    EXPECT_LE(applied, appended.load() + 1);
    failed |= !log->Trim("f", applied).ok();
  }
  writer.join();
  EXPECT_EQ(ReadAll(*log, "f", 0).back(), kEntries);
}

// The RocksDB store moves the log entries that builds before the segment
// log kept in RocksDB into it, once.
TEST(SegmentLogTest, TheStoreMovesAnEarlierBuildsLogOutOfRocksDb) {
  TempDir dir;
  const std::string path = dir.path() + "/db";
  {
    RocksDbStoreOptions options;
    options.path = path;
    ASSERT_TRUE(OpenRocksDbStore(options).ok());  // the format key
    rocksdb::Options raw_options;
    rocksdb::DB* raw = nullptr;
    ASSERT_TRUE(rocksdb::DB::Open(raw_options, path, &raw).ok());
    std::unique_ptr<rocksdb::DB> db(raw);
    for (uint64_t s = 4; s <= 9; ++s) {
      const std::string key = keys::LogKey("f", s);
      ASSERT_TRUE(
          db->Put(rocksdb::WriteOptions(), key,
                  EncodeLoggedRecord(engine::UploadRecord{EntryTraces(s)}))
              .ok());
    }
  }
  for (int open = 0; open < 2; ++open) {
    RocksDbStoreOptions options;
    options.path = path;
    absl::StatusOr<LocalStorage> storage = OpenLocalStorage(options);
    ASSERT_TRUE(storage.ok()) << storage.status();
    absl::StatusOr<std::vector<engine::LogEntry>> read =
        storage->log->Read("f", 0, 100);
    ASSERT_TRUE(read.ok()) << read.status();
    ASSERT_EQ(read->size(), 6u);
    EXPECT_EQ(read->front().sequence, 4u);
    EXPECT_EQ(read->back().traces()[2].seq, 92u);
    EXPECT_EQ(storage->log->Fleets()->size(), 1u);
  }
  rocksdb::DB* raw = nullptr;
  ASSERT_TRUE(
      rocksdb::DB::OpenForReadOnly(rocksdb::Options(), path, &raw).ok());
  std::unique_ptr<rocksdb::DB> db(raw);
  std::string value;
  EXPECT_TRUE(db->Get(rocksdb::ReadOptions(), keys::LogKey("f", 4), &value)
                  .IsNotFound());
}

}  // namespace
}  // namespace fleetmem::storage
