#include "services/storage/segment_log.h"

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <xxhash.h>

#include <algorithm>
#include <bit>
#include <cerrno>
#include <charconv>
#include <cstring>
#include <filesystem>
#include <optional>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "services/common/log.h"
#include "services/core/absl_view.h"
#include "services/core/validation.h"
#include "services/storage/file_io.h"
#include "services/storage/record_codec.h"

namespace fleetmem::storage {
namespace {

static_assert(std::endian::native == std::endian::little,
              "the segment format is little-endian; so is this host");

constexpr char kMagic[4] = {'F', 'M', 'L', 'G'};
// magic | hash | segment | sequence | payload bytes
constexpr size_t kHashAt = 4;
constexpr size_t kHashedFrom = 12;
constexpr size_t kHeaderBytes = 32;
constexpr std::string_view kFleetPrefix = "f-";
constexpr std::string_view kSparePrefix = "spare-";
constexpr std::string_view kSuffix = ".seg";
constexpr size_t kCopyChunk = size_t{1} << 20;
// O_DIRECT writes whole blocks at block offsets. Each append ends with a
// padding record (sequence 0): to the next block where O_DIRECT is used.
constexpr size_t kBlock = 4096;
constexpr size_t RoundUp(size_t bytes) {
  return (bytes + kBlock - 1) / kBlock * kBlock;
}

using file_io::ErrnoText;
using file_io::IoError;
using file_io::SyncDirectory;

template <typename T>
T Load(const char* at) {
  T value;
  std::memcpy(&value, at, sizeof(T));
  return value;
}
template <typename T>
void Store(char* at, T value) {
  std::memcpy(at, &value, sizeof(T));
}

std::string SegmentName(uint64_t first) {
  return absl::StrFormat("%020d%s", first, kSuffix);
}

// A file descriptor, closed when the last user lets go.
struct File {
  explicit File(int fd) : fd(fd) {}
  ~File() { ::close(fd); }
  File(const File&) = delete;
  File& operator=(const File&) = delete;
  const int fd;
};

// Creates `path` (not its parents) and syncs its parent; OK if it exists.
absl::Status MakeDirectory(const std::string& path) {
  if (::mkdir(path.c_str(), 0755) != 0) {
    if (errno == EEXIST) return absl::OkStatus();
    return IoError(errno, absl::StrCat("create directory '", path, "'"));
  }
  return SyncDirectory(std::filesystem::path(path).parent_path().string());
}

absl::Status WriteAll(int fd, std::string_view bytes, uint64_t offset,
                      std::string_view what) {
  while (!bytes.empty()) {
    const ssize_t n =
        ::pwrite(fd, bytes.data(), bytes.size(), static_cast<off_t>(offset));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return IoError(n < 0 ? errno : EIO, what);
    bytes.remove_prefix(static_cast<size_t>(n));
    offset += static_cast<uint64_t>(n);
  }
  return absl::OkStatus();
}

// Reads up to `size` bytes at `offset` (fewer at the end of the file).
absl::StatusOr<std::string> ReadAt(int fd, uint64_t offset, size_t size,
                                   std::string_view what) {
  std::string out(size, '\0');
  size_t done = 0;
  while (done < size) {
    const ssize_t n = ::pread(fd, out.data() + done, size - done,
                              static_cast<off_t>(offset + done));
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) return IoError(errno, what);
    if (n == 0) break;
    done += static_cast<size_t>(n);
  }
  out.resize(done);
  return out;
}

// Writes the header of the record whose payload follows it at `at`.
void WriteHeader(char* at, uint64_t segment, uint64_t sequence,
                 uint32_t payload) {
  std::memcpy(at, kMagic, sizeof(kMagic));
  Store<uint64_t>(at + 12, segment);
  Store<uint64_t>(at + 20, sequence);
  Store<uint32_t>(at + 28, payload);
  Store<uint64_t>(
      at + kHashAt,
      XXH3_64bits(at + kHashedFrom, kHeaderBytes - kHashedFrom + payload));
}

// Memory aligned for O_DIRECT.
struct Aligned {
  void operator()(char* p) const { std::free(p); }
};
using AlignedBuffer = std::unique_ptr<char, Aligned>;
AlignedBuffer Allocate(size_t bytes) {
  return AlignedBuffer(
      static_cast<char*>(std::aligned_alloc(kBlock, RoundUp(bytes))));
}

// True if `record` (header and payload) is whole, intact and the record
// `sequence` of `segment`.
bool Intact(std::string_view record, uint64_t segment, uint64_t sequence) {
  if (record.size() < kHeaderBytes ||
      std::memcmp(record.data(), kMagic, sizeof(kMagic)) != 0 ||
      Load<uint64_t>(record.data() + 12) != segment ||
      Load<uint64_t>(record.data() + 20) != sequence ||
      Load<uint32_t>(record.data() + 28) != record.size() - kHeaderBytes) {
    return false;
  }
  return XXH3_64bits(record.data() + kHashedFrom,
                     record.size() - kHashedFrom) ==
         Load<uint64_t>(record.data() + kHashAt);
}

// The record at `at` in `data`, if it is whole, intact and of `segment`,
// and a padding record or entry `expected` (with `or_later`: any entry from
// `expected` on): its sequence (0: padding) and size.
struct Found {
  uint64_t sequence = 0;
  uint64_t offset = 0;
  uint64_t size = 0;
};
std::optional<Found> RecordAt(std::string_view data, uint64_t at,
                              uint64_t segment, uint64_t expected,
                              bool or_later) {
  if (at + kHeaderBytes > data.size()) return std::nullopt;
  const char* header = data.data() + at;
  if (std::memcmp(header, kMagic, sizeof(kMagic)) != 0 ||
      Load<uint64_t>(header + 12) != segment) {
    return std::nullopt;
  }
  const uint64_t sequence = Load<uint64_t>(header + 20);
  if (sequence != 0 &&
      (or_later ? sequence < expected : sequence != expected)) {
    return std::nullopt;
  }
  const uint64_t size = kHeaderBytes + Load<uint32_t>(header + 28);
  if (at + size > data.size() ||
      !Intact(data.substr(at, size), segment, sequence)) {
    return std::nullopt;
  }
  return Found{sequence, at, size};
}

// The first intact record of `segment` (padding, or an entry from
// `expected` on) that starts after `at`.
std::optional<Found> NextRecordAfter(std::string_view data, uint64_t at,
                                     uint64_t segment, uint64_t expected) {
  for (uint64_t from = at + 1; from + kHeaderBytes <= data.size();) {
    const void* hit = ::memmem(data.data() + from, data.size() - from, kMagic,
                               sizeof(kMagic));
    if (hit == nullptr) break;
    const uint64_t candidate =
        static_cast<uint64_t>(static_cast<const char*>(hit) - data.data());
    if (std::optional<Found> found =
            RecordAt(data, candidate, segment, expected, /*or_later=*/true)) {
      return found;
    }
    from = candidate + 1;
  }
  return std::nullopt;
}

// What a segment file holds: its entries in order, where its whole records
// end, and the entries missing between two intact records (damage).
struct ScannedSegment {
  struct Gap {
    uint64_t first, last;  // sequences
    uint64_t offset;       // where the damage begins
  };
  std::vector<Found> entries;
  uint64_t end = 0;
  std::vector<Gap> gaps;
  // The entry whose record the segment ends in, cut short or failing its
  // checksum (0: it ends cleanly): a write torn by a crash, never
  // acknowledged, or damage to the last record, which cannot be told apart.
  uint64_t cut_entry = 0;
};

// True if a record header of `segment` naming entry `sequence` starts at
// `at` (whatever follows it).
bool HeaderNames(std::string_view data, uint64_t at, uint64_t segment,
                 uint64_t sequence) {
  return at + kHeaderBytes <= data.size() &&
         std::memcmp(data.data() + at, kMagic, sizeof(kMagic)) == 0 &&
         Load<uint64_t>(data.data() + at + 12) == segment &&
         Load<uint64_t>(data.data() + at + 20) == sequence;
}

ScannedSegment ScanSegment(std::string_view data, uint64_t first) {
  ScannedSegment out;
  uint64_t at = 0;
  uint64_t expected = first;
  while (true) {
    std::optional<Found> record =
        RecordAt(data, at, first, expected, /*or_later=*/false);
    if (!record) {
      // A torn tail (nothing intact follows: the segment ends here), or
      // damage followed by intact records.
      record = NextRecordAfter(data, at, first, expected);
      if (!record) {
        if (HeaderNames(data, at, first, expected)) out.cut_entry = expected;
        break;
      }
      if (record->sequence > expected) {
        out.gaps.push_back({expected, record->sequence - 1, at});
      } else if (record->sequence == 0) {
        // The padding record that ends every append: the append was
        // written whole, so the record before it that fails is damaged,
        // not torn. (Were more records damaged, the next entry found
        // reports the rest.)
        out.gaps.push_back({expected, expected, at});
        ++expected;
      }
    }
    if (record->sequence != 0) {
      out.entries.push_back(*record);
      expected = record->sequence + 1;
    }
    at = record->offset + record->size;
    out.end = at;
  }
  return out;
}

// Where one record of a segment lies.
struct SegmentLogRecord {
  uint64_t sequence, offset, size;
};

}  // namespace

struct SegmentLog::Segment {
  uint64_t first = 0;  // its first sequence: its name
  std::string path;
  // The descriptor appends write through (O_DIRECT where the filesystem
  // has it), held by the segment appends go to only: a fleet's backlog may
  // span a hundred segments, and readers open the file for each read.
  std::shared_ptr<const File> file;
  bool direct = false;
  uint64_t end = 0;  // bytes of whole records and padding (fleet's mu)
  using Record = SegmentLogRecord;
  std::vector<Record> records;  // ascending (fleet's mu)

  uint64_t last() const {
    return records.empty() ? 0 : records.back().sequence;
  }
};

// Opens the segment's file for appends (O_DIRECT where the filesystem
// allows it: an entry is read back once, by the applier, so copying it
// into the page cache on the acknowledgement's path buys nothing).
absl::Status SegmentLog::OpenForAppends(Segment& segment) {
  const int flags = O_RDWR | O_CLOEXEC | O_CREAT;
  int fd = ::open(segment.path.c_str(), flags | O_DIRECT, 0644);
  segment.direct = fd >= 0;
  if (fd < 0 && errno == EINVAL) {
    fd = ::open(segment.path.c_str(), flags, 0644);  // e.g. tmpfs
  }
  if (fd < 0) {
    return IoError(errno, absl::StrCat("open '", segment.path, "'"));
  }
  segment.file = std::make_shared<File>(fd);
  return absl::OkStatus();
}

namespace {

// Opens `path` for reading (through the page cache).
absl::StatusOr<std::unique_ptr<File>> OpenForReads(const std::string& path) {
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) return IoError(errno, absl::StrCat("open '", path, "'"));
  return std::make_unique<File>(fd);
}

}  // namespace

struct SegmentLog::Fleet {
  std::string id;
  std::string path;
  absl::Mutex mu;
  // Ascending; appends go to the last one unless `sealed`.
  std::vector<std::shared_ptr<Segment>> segments ABSL_GUARDED_BY(mu);
  // A failed write left the last segment's end undefined: the next append
  // starts another segment.
  bool sealed ABSL_GUARDED_BY(mu) = false;
  std::vector<std::string> spares ABSL_GUARDED_BY(mu);
  uint64_t next_spare ABSL_GUARDED_BY(mu) = 0;
  // Entries found damaged and passed over.
  std::vector<engine::LostLogEntries> losses ABSL_GUARDED_BY(mu);

  // The last sequence the fleet's log gave (0: none): its last record's,
  // or the one before the first of a segment left empty (a failed first
  // append), so that no sequence is given twice.
  uint64_t Last() const ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
    uint64_t last = 0;
    for (const std::shared_ptr<Segment>& segment : segments) {
      last = std::max(last, segment->records.empty() ? segment->first - 1
                                                     : segment->last());
    }
    return last;
  }

  // Records and logs (an error) the loss of entries first..last.
  void Lose(uint64_t first, uint64_t last, std::string detail)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
    FLEETMEM_LOG(kError) << "DATA_LOSS: ingest log of fleet \"" << id
                         << "\": acknowledged entries " << first << ".." << last
                         << " are lost (" << detail
                         << "); the entries after them are applied";
    losses.push_back({first, last, std::move(detail)});
  }

  // At load, with `gaps[i]` the damaged runs ScanSegment found in
  // segments[i]: sequences run on across segments (each starts right after
  // the last entry before it; a write that failed was undone and written
  // again at the start of the next segment, so what the failed one left,
  // if its undo did not reach the disk, is not read), and the entries of
  // the gaps and of a damaged segment end are lost.
  void Stitch(const std::vector<std::vector<ScannedSegment::Gap>>& gaps)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu) {
    uint64_t last = 0;
    for (size_t i = 0; i < segments.size(); ++i) {
      Segment& segment = *segments[i];
      const uint64_t next =
          i + 1 < segments.size() ? segments[i + 1]->first : UINT64_MAX;
      while (!segment.records.empty() && segment.last() >= next) {
        segment.records.pop_back();
      }
      if (last != 0 && segment.first > last + 1) {
        Lose(last + 1, segment.first - 1,
             absl::StrCat("the end of the segment before '", segment.path,
                          "' is damaged"));
      }
      last = segment.records.empty() ? segment.first - 1 : segment.last();
      for (const ScannedSegment::Gap& gap : gaps[i]) {
        if (gap.first >= next) continue;
        const uint64_t lost_through = std::min(gap.last, next - 1);
        Lose(
            gap.first, lost_through,
            absl::StrCat("'", segment.path, "' is damaged at byte ", gap.offset,
                         ": the records there fail their checksum or "
                         "frame"));
        last = std::max(last, lost_through);
      }
    }
  }
};

std::vector<engine::LostLogEntries> SegmentLog::Losses(
    std::string_view fleet_id) {
  Fleet* fleet = Find(fleet_id);
  if (fleet == nullptr) return {};
  absl::MutexLock lock(&fleet->mu);
  return fleet->losses;
}

SegmentLog::SegmentLog(SegmentLogOptions options)
    : options_(std::move(options)) {}

SegmentLog::~SegmentLog() = default;

absl::StatusOr<std::unique_ptr<SegmentLog>> SegmentLog::Open(
    SegmentLogOptions options) {
  if (options.directory.empty()) {
    return absl::InvalidArgumentError("SegmentLogOptions.directory is empty");
  }
  if (options.segment_bytes == 0) {
    return absl::InvalidArgumentError("segment_bytes must be positive");
  }
  if (absl::Status made = MakeDirectory(options.directory); !made.ok()) {
    return made;
  }
  std::unique_ptr<SegmentLog> log(new SegmentLog(std::move(options)));
  std::error_code error;
  std::vector<std::pair<std::string, std::string>> fleets;
  for (const auto& entry :
       std::filesystem::directory_iterator(log->options_.directory, error)) {
    const std::string name = entry.path().filename().string();
    if (!entry.is_directory() || !name.starts_with(kFleetPrefix)) continue;
    const std::string fleet_id = name.substr(kFleetPrefix.size());
    if (!core::ValidateId("fleet_id", fleet_id).ok()) continue;
    fleets.emplace_back(fleet_id, entry.path().string());
  }
  if (error) {
    return absl::UnavailableError(absl::StrCat(
        "list '", log->options_.directory, "': ", error.message()));
  }
  for (const auto& [fleet_id, path] : fleets) {
    if (absl::Status loaded = log->LoadFleet(fleet_id, path); !loaded.ok()) {
      return loaded;
    }
  }
  return log;
}

namespace {

// A fleet's segment files under `path`, by their first sequence, and its
// spare files (with the number after the highest).
struct SegmentFiles {
  std::vector<std::pair<uint64_t, std::string>> segments;  // ascending
  std::vector<std::string> spares;
  uint64_t next_spare = 0;
};

absl::StatusOr<SegmentFiles> ListSegmentFiles(const std::string& path) {
  SegmentFiles files;
  std::error_code error;
  for (const auto& entry : std::filesystem::directory_iterator(path, error)) {
    const std::string name = entry.path().filename().string();
    if (!name.ends_with(kSuffix)) continue;
    const std::string_view stem(name.data(), name.size() - kSuffix.size());
    uint64_t number = 0;
    const bool spare = stem.starts_with(kSparePrefix);
    const std::string_view digits =
        spare ? stem.substr(kSparePrefix.size()) : stem;
    const auto [end, parsed] =
        std::from_chars(digits.data(), digits.data() + digits.size(), number);
    if (parsed != std::errc() || end != digits.data() + digits.size()) {
      continue;
    }
    if (spare) {
      files.spares.push_back(entry.path().string());
      files.next_spare = std::max(files.next_spare, number + 1);
    } else {
      files.segments.emplace_back(number, entry.path().string());
    }
  }
  if (error) {
    return absl::UnavailableError(
        absl::StrCat("list '", path, "': ", error.message()));
  }
  std::sort(files.segments.begin(), files.segments.end());
  return files;
}

// The records of the segment file at `path`, whose first entry is `first`.
absl::StatusOr<ScannedSegment> ScanSegmentFile(const std::string& path,
                                               uint64_t first) {
  absl::StatusOr<std::unique_ptr<File>> reader = OpenForReads(path);
  if (!reader.ok()) return reader.status();
  const int fd = (*reader)->fd;
  struct stat info;
  if (::fstat(fd, &info) != 0) {
    return IoError(errno, absl::StrCat("stat '", path, "'"));
  }
  absl::StatusOr<std::string> data =
      ReadAt(fd, 0, static_cast<size_t>(info.st_size), path);
  if (!data.ok()) return data.status();
  return ScanSegment(*data, first);
}

}  // namespace

absl::Status SegmentLog::LoadFleet(const std::string& fleet_id,
                                   const std::string& path) {
  Fleet& fleet = FindOrMake(fleet_id);
  absl::MutexLock lock(&fleet.mu);
  absl::StatusOr<SegmentFiles> files = ListSegmentFiles(path);
  if (!files.ok()) return files.status();
  fleet.spares = std::move(files->spares);
  fleet.next_spare = files->next_spare;
  std::vector<std::vector<ScannedSegment::Gap>> gaps;
  for (const auto& [first, file_path] : files->segments) {
    absl::StatusOr<ScannedSegment> scanned = ScanSegmentFile(file_path, first);
    if (!scanned.ok()) return scanned.status();
    auto segment = std::make_shared<Segment>();
    segment->first = first;
    segment->path = file_path;
    for (const Found& entry : scanned->entries) {
      segment->records.push_back({entry.sequence, entry.offset, entry.size});
    }
    segment->end = scanned->end;
    // (Where a later segment follows, the gap before it is reported by
    // Stitch.)
    if (scanned->cut_entry != 0 && file_path == files->segments.back().second) {
      FLEETMEM_LOG(kWarning)
          << "ingest log of fleet \"" << fleet_id << "\": '" << file_path
          << "' ends in entry " << scanned->cut_entry
          << ", cut short or failing its checksum: the write in flight at a "
             "crash (never acknowledged), or damage to the segment's last "
             "record (which cannot be told apart there); it is not applied";
    }
    gaps.push_back(std::move(scanned->gaps));
    fleet.segments.push_back(std::move(segment));
  }
  fleet.Stitch(gaps);
  // The last segment may end in a torn write: appends after a restart start
  // a new segment.
  fleet.sealed = true;
  return absl::OkStatus();
}

SegmentLog::Fleet* SegmentLog::Find(std::string_view fleet_id) {
  absl::MutexLock lock(&mu_);
  auto it = fleets_.find(fleet_id);
  return it == fleets_.end() ? nullptr : it->second.get();
}

std::vector<SegmentLog::Fleet*> SegmentLog::AllFleets() {
  absl::MutexLock lock(&mu_);
  std::vector<Fleet*> fleets;
  for (const auto& [id, fleet] : fleets_) fleets.push_back(fleet.get());
  return fleets;
}

SegmentLog::Fleet& SegmentLog::FindOrMake(std::string_view fleet_id) {
  absl::MutexLock lock(&mu_);
  auto [it, inserted] = fleets_.try_emplace(std::string(fleet_id));
  if (inserted) {
    it->second = std::make_unique<Fleet>();
    it->second->id = std::string(fleet_id);
    it->second->path =
        absl::StrCat(options_.directory, "/", V(kFleetPrefix), V(fleet_id));
  }
  return *it->second;
}

absl::StatusOr<std::shared_ptr<SegmentLog::Segment>> SegmentLog::StartSegment(
    Fleet& fleet, uint64_t first) {
  if (absl::Status made = MakeDirectory(fleet.path); !made.ok()) return made;
  auto segment = std::make_shared<Segment>();
  segment->first = first;
  segment->path = absl::StrCat(fleet.path, "/", SegmentName(first));
  std::string spare;
  {
    absl::MutexLock lock(&fleet.mu);
    if (!fleet.spares.empty()) {
      spare = std::move(fleet.spares.back());
      fleet.spares.pop_back();
    }
  }
  if (!spare.empty() && ::rename(spare.c_str(), segment->path.c_str()) != 0) {
    FLEETMEM_LOG(kWarning) << "cannot reuse '" << spare
                           << "': " << ErrnoText(errno);
  }
  // Not truncated: a reused file (or a segment that a failed first append
  // left) holds no record of this segment, and overwriting is what keeps
  // fdatasync cheap.
  if (absl::Status opened = OpenForAppends(*segment); !opened.ok()) {
    return opened;
  }
  if (absl::Status synced = SyncDirectory(fleet.path); !synced.ok()) {
    return synced;
  }
  return segment;
}

absl::StatusOr<SegmentLog::Target> SegmentLog::TargetOf(
    Fleet& fleet, std::string_view fleet_id, uint64_t first_sequence) {
  Target target;
  {
    absl::MutexLock lock(&fleet.mu);
    if (!fleet.segments.empty()) {
      const std::shared_ptr<Segment>& last = fleet.segments.back();
      // A segment's records run on from its first sequence.
      const uint64_t next =
          last->records.empty() ? last->first : last->last() + 1;
      if (!fleet.sealed && last->end < options_.segment_bytes &&
          next == first_sequence) {
        target.segment = last;
        target.offset = last->end;
      } else if (last->records.empty() && last->first == first_sequence) {
        // A failed first append left it empty: start it again.
        target.segment = last;
      }
    }
  }
  const auto not_stored = [fleet_id](const absl::Status& status) {
    return absl::Status(
        status.code(),
        absl::StrCat("append to the ingest log of fleet \"", V(fleet_id),
                     "\": ", status.message(), " (nothing of it was stored)"));
  };
  if (target.segment == nullptr) {
    absl::StatusOr<std::shared_ptr<Segment>> made =
        StartSegment(fleet, first_sequence);
    if (!made.ok()) return not_stored(made.status());
    target.segment = *std::move(made);
    target.started = true;
    return target;
  }
  if (target.segment->file == nullptr) {
    // A segment found at Open: no descriptor for appends yet.
    if (absl::Status opened = OpenForAppends(*target.segment); !opened.ok()) {
      return not_stored(opened);
    }
  }
  absl::MutexLock lock(&fleet.mu);
  fleet.sealed = false;
  return target;
}

namespace {

// An append's bytes: its records, then a padding record (sequence 0) that
// ends it, to the next block with O_DIRECT, bare otherwise. A reader that
// finds the padding after a record failing its checksum knows the append
// was written whole (so the record is damaged, not torn).
struct Encoded {
  AlignedBuffer buffer;
  size_t size = 0;
  std::vector<SegmentLogRecord> records;  // offsets in the segment
};

absl::StatusOr<Encoded> Encode(uint64_t first_sequence,
                               const std::vector<LoggedRecordBytes>& payloads,
                               uint64_t bytes, uint64_t segment_first,
                               bool direct, uint64_t offset) {
  Encoded out;
  out.size = bytes + kHeaderBytes;
  if (direct) out.size = RoundUp(out.size);
  out.buffer = Allocate(out.size);
  if (out.buffer == nullptr) {
    return absl::ResourceExhaustedError(
        absl::StrCat("no memory for an append of ", out.size,
                     " bytes (nothing was stored)"));
  }
  char* buffer = out.buffer.get();
  size_t at = 0;
  for (size_t i = 0; i < payloads.size(); ++i) {
    const LoggedRecordBytes& payload = payloads[i];
    out.records.push_back(
        {first_sequence + i, offset + at, kHeaderBytes + payload.size()});
    payload.WriteTo(buffer + at + kHeaderBytes);
    WriteHeader(buffer + at, segment_first, first_sequence + i,
                static_cast<uint32_t>(payload.size()));
    at += kHeaderBytes + payload.size();
  }
  if (out.size > at) {
    std::memset(buffer + at, 0, out.size - at);
    WriteHeader(buffer + at, segment_first, 0,
                static_cast<uint32_t>(out.size - at - kHeaderBytes));
  }
  return out;
}

// Undoes an append that failed: zeros over what of it reached the file, so
// that a reader after a restart finds none of its records (the segment
// ends where it began; a record of it found later would read as damage
// before it). True if the zeros are durable.
bool Unwrite(int fd, const std::string& path, Encoded& append, uint64_t offset,
             bool direct) {
  struct stat info;
  uint64_t reached = append.size;
  if (::fstat(fd, &info) == 0) {
    const uint64_t file_size = static_cast<uint64_t>(info.st_size);
    reached = file_size > offset
                  ? std::min<uint64_t>(append.size, file_size - offset)
                  : 0;
  }
  if (direct) reached = RoundUp(reached);
  std::memset(append.buffer.get(), 0, append.size);
  return WriteAll(fd, std::string_view(append.buffer.get(), reached), offset,
                  path)
             .ok() &&
         ::fdatasync(fd) == 0;
}

}  // namespace

absl::StatusOr<uint64_t> SegmentLog::NextSequence(
    Fleet& fleet, const engine::AppendOptions& options) {
  uint64_t last = 0;
  {
    absl::MutexLock lock(&fleet.mu);
    last = fleet.Last();
  }
  if (options.only_first && last > 0) {
    return absl::FailedPreconditionError(
        absl::StrCat("the log of fleet \"", fleet.id,
                     "\" has entries already (nothing was appended)"));
  }
  return std::max(last, options.above) + 1;
}

absl::StatusOr<std::vector<engine::AppendedEntry>> SegmentLog::Append(
    std::string_view fleet_id, std::span<const engine::LogAppend> entries,
    const engine::AppendOptions& options) {
  std::vector<engine::AppendedEntry> appended;
  if (entries.empty()) return appended;
  // Checked at the edge already; here because the id names a directory,
  // and Open reads back only the fleets whose directory names a valid id.
  if (absl::Status valid = core::ValidateId("fleet_id", fleet_id);
      !valid.ok()) {
    return valid;
  }
  std::vector<LoggedRecordBytes> payloads;
  payloads.reserve(entries.size());
  uint64_t bytes = 0;
  for (const engine::LogAppend& entry : entries) {
    payloads.emplace_back(entry.record);
    bytes += kHeaderBytes + payloads.back().size();
  }
  if (options_.check_room) {
    if (absl::Status room = options_.check_room(fleet_id, bytes); !room.ok()) {
      return room;
    }
  }
  Fleet& fleet = FindOrMake(fleet_id);
  absl::StatusOr<uint64_t> next = NextSequence(fleet, options);
  if (!next.ok()) return next.status();
  const uint64_t first = *next;
  absl::StatusOr<Target> target = TargetOf(fleet, fleet_id, first);
  if (!target.ok()) return target.status();
  Segment& segment = *target->segment;
  absl::StatusOr<Encoded> append = Encode(first, payloads, bytes, segment.first,
                                          segment.direct, target->offset);
  if (!append.ok()) return append.status();
  const int fd = segment.file->fd;
  absl::Status written =
      WriteAll(fd, std::string_view(append->buffer.get(), append->size),
               target->offset, segment.path);
  if (written.ok() && ::fdatasync(fd) != 0) {
    written = IoError(errno, absl::StrCat("fdatasync '", segment.path, "'"));
  }
  if (!written.ok()) {
    const bool undone =
        Unwrite(fd, segment.path, *append, target->offset, segment.direct);
    {
      // The next append starts another segment.
      absl::MutexLock lock(&fleet.mu);
      fleet.sealed = true;
      if (target->started) fleet.segments.push_back(target->segment);
    }
    FLEETMEM_LOG(kError) << "append to the ingest log of fleet \"" << fleet_id
                         << "\" failed: " << written
                         << (undone ? "" : " (and could not be undone)");
    return absl::Status(
        written.code(),
        absl::StrCat(
            "append to the ingest log of fleet \"", V(fleet_id),
            "\": ", written.message(),
            undone ? " (nothing of it was stored)"
                   : " (it could not be undone: the entries may be applied "
                     "after a restart, as if acknowledged)"));
  }
  absl::MutexLock lock(&fleet.mu);
  if (target->started) {
    // The segment before takes no more appends: its descriptor goes. The
    // new one takes the appends after this one (until now a restart left
    // the fleet sealed, and every append after it started a segment).
    if (!fleet.segments.empty()) fleet.segments.back()->file.reset();
    fleet.segments.push_back(target->segment);
    fleet.sealed = false;
  }
  segment.end = target->offset + append->size;
  segment.records.insert(segment.records.end(), append->records.begin(),
                         append->records.end());
  for (size_t i = 0; i < entries.size(); ++i) {
    appended.push_back({first + i, false});
  }
  return appended;
}

absl::StatusOr<std::vector<engine::LogEntry>> SegmentLog::Read(
    std::string_view fleet_id, uint64_t after, size_t max_entries) {
  std::vector<engine::LogEntry> out;
  Fleet* fleet = Find(fleet_id);
  if (fleet == nullptr || max_entries == 0) return out;
  struct Wanted {
    std::shared_ptr<Segment> segment;
    uint64_t sequence, offset, size;
  };
  std::vector<Wanted> wanted;
  {
    absl::MutexLock lock(&fleet->mu);
    for (const std::shared_ptr<Segment>& segment : fleet->segments) {
      if (segment->records.empty() || segment->last() <= after) continue;
      const auto& records = segment->records;
      auto it =
          std::upper_bound(records.begin(), records.end(), after,
                           [](uint64_t value, const Segment::Record& record) {
                             return value < record.sequence;
                           });
      for (; it != records.end() && wanted.size() < max_entries; ++it) {
        wanted.push_back({segment, it->sequence, it->offset, it->size});
      }
      if (wanted.size() == max_entries) break;
    }
  }
  out.reserve(wanted.size());
  std::unique_ptr<File> reader;  // of the segment read last
  const Segment* open = nullptr;
  for (const Wanted& want : wanted) {
    if (open != want.segment.get()) {
      absl::StatusOr<std::unique_ptr<File>> opened =
          OpenForReads(want.segment->path);
      if (!opened.ok()) return opened.status();
      reader = *std::move(opened);
      open = want.segment.get();
    }
    absl::StatusOr<std::string> record =
        ReadAt(reader->fd, want.offset, want.size, want.segment->path);
    if (!record.ok()) return record.status();
    const std::string where =
        absl::StrCat("ingest log of fleet \"", V(fleet_id), "\", entry ",
                     want.sequence, " in '", want.segment->path, "'");
    if (!Intact(*record, want.segment->first, want.sequence)) {
      // Damaged since Open read it: passed over, reported, and taken out of
      // the segment's index so that it is reported once.
      absl::MutexLock lock(&fleet->mu);
      auto& records = want.segment->records;
      auto it =
          std::lower_bound(records.begin(), records.end(), want.sequence,
                           [](const Segment::Record& record, uint64_t value) {
                             return record.sequence < value;
                           });
      if (it != records.end() && it->sequence == want.sequence) {
        records.erase(it);
        fleet->Lose(
            want.sequence, want.sequence,
            absl::StrCat(where, " fails its checksum or frame when read"));
      }
      continue;
    }
    absl::StatusOr<engine::StoredRecord> decoded = DecodeLoggedRecord(
        where, std::string_view(*record).substr(kHeaderBytes));
    if (!decoded.ok()) return decoded.status();
    out.push_back({want.sequence, std::string(), *std::move(decoded)});
  }
  return out;
}

absl::Status SegmentLog::Trim(std::string_view fleet_id, uint64_t through) {
  absl::MutexLock trims(&trim_mu_);
  Fleet* fleet = Find(fleet_id);
  if (fleet == nullptr) return absl::OkStatus();
  auto removable = [&]() ABSL_EXCLUSIVE_LOCKS_REQUIRED(fleet->mu) {
    size_t count = 0;
    while (count + 1 < fleet->segments.size() &&
           fleet->segments[count]->last() <= through) {
      ++count;
    }
    return count;
  };
  {
    absl::MutexLock lock(&fleet->mu);
    if (removable() == 0) return absl::OkStatus();
  }
  if (options_.before_trim) {
    if (absl::Status durable = options_.before_trim(); !durable.ok()) {
      return durable;
    }
  }
  std::vector<std::shared_ptr<Segment>> removed;
  {
    absl::MutexLock lock(&fleet->mu);
    const size_t count = removable();
    removed.assign(fleet->segments.begin(), fleet->segments.begin() + count);
    fleet->segments.erase(fleet->segments.begin(),
                          fleet->segments.begin() + count);
  }
  // Oldest first, each removal durable before the next: a crash leaves the
  // segments after some point, never a gap.
  for (const std::shared_ptr<Segment>& segment : removed) {
    std::string spare;
    {
      absl::MutexLock lock(&fleet->mu);
      if (fleet->spares.size() < options_.spare_segments) {
        spare = absl::StrCat(fleet->path, "/", V(kSparePrefix),
                             fleet->next_spare++, V(kSuffix));
      }
    }
    const bool kept =
        !spare.empty() && ::rename(segment->path.c_str(), spare.c_str()) == 0;
    if (kept) {
      absl::MutexLock lock(&fleet->mu);
      fleet->spares.push_back(spare);
    } else if (::unlink(segment->path.c_str()) != 0 && errno != ENOENT) {
      return IoError(errno, absl::StrCat("remove '", segment->path, "'"));
    }
    if (absl::Status synced = SyncDirectory(fleet->path); !synced.ok()) {
      return synced;
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<engine::LogBounds> SegmentLog::Bounds(
    std::string_view fleet_id) {
  engine::LogBounds bounds;
  Fleet* fleet = Find(fleet_id);
  if (fleet == nullptr) return bounds;
  absl::MutexLock lock(&fleet->mu);
  bounds.last = fleet->Last();
  bounds.first = bounds.last + 1;
  for (const std::shared_ptr<Segment>& segment : fleet->segments) {
    if (!segment->records.empty()) {
      bounds.first = segment->records.front().sequence;
      break;
    }
  }
  if (bounds.last == 0) bounds.first = 0;
  return bounds;
}

absl::StatusOr<std::vector<std::string>> SegmentLog::Fleets() {
  std::vector<std::string> fleets;
  for (Fleet* fleet : AllFleets()) {
    absl::MutexLock lock(&fleet->mu);
    if (fleet->Last() > 0) fleets.push_back(fleet->id);
  }
  return fleets;
}

uint64_t SegmentLog::Bytes() {
  const std::vector<Fleet*> fleets = AllFleets();
  uint64_t bytes = 0;
  for (Fleet* fleet : fleets) {
    absl::MutexLock lock(&fleet->mu);
    for (const std::shared_ptr<Segment>& segment : fleet->segments) {
      bytes += segment->end;
    }
  }
  return bytes;
}

uint64_t SegmentLog::SpareBytes() {
  uint64_t bytes = 0;
  for (Fleet* fleet : AllFleets()) {
    absl::MutexLock lock(&fleet->mu);
    for (const std::string& spare : fleet->spares) {
      std::error_code error;
      const uintmax_t size = std::filesystem::file_size(spare, error);
      if (!error) bytes += size;
    }
  }
  return bytes;
}

uint64_t SegmentLog::DropSpares() {
  uint64_t freed = 0;
  for (Fleet* fleet : AllFleets()) {
    std::vector<std::string> spares;
    {
      absl::MutexLock lock(&fleet->mu);
      spares.swap(fleet->spares);
    }
    for (const std::string& spare : spares) {
      std::error_code error;
      const uintmax_t size = std::filesystem::file_size(spare, error);
      if (::unlink(spare.c_str()) == 0 && !error) freed += size;
    }
  }
  if (freed > 0) {
    FLEETMEM_LOG(kWarning) << "disk short: deleted the ingest log's spare "
                              "segments ("
                           << freed << " bytes)";
  }
  return freed;
}

absl::Status SegmentLog::CopyTo(const std::string& directory,
                                const std::function<absl::Status()>& first) {
  absl::MutexLock trims(&trim_mu_);
  if (first) {
    if (absl::Status done = first(); !done.ok()) return done;
  }
  if (absl::Status made = MakeDirectory(directory); !made.ok()) return made;
  const std::vector<Fleet*> fleets = AllFleets();
  for (Fleet* fleet : fleets) {
    std::vector<std::pair<std::shared_ptr<Segment>, uint64_t>> segments;
    {
      absl::MutexLock lock(&fleet->mu);
      for (const std::shared_ptr<Segment>& segment : fleet->segments) {
        if (!segment->records.empty()) {
          segments.emplace_back(segment, segment->end);
        }
      }
    }
    if (segments.empty()) continue;
    const std::string fleet_dir =
        absl::StrCat(directory, "/", V(kFleetPrefix), fleet->id);
    if (absl::Status made = MakeDirectory(fleet_dir); !made.ok()) return made;
    for (const auto& [segment, end] : segments) {
      const std::string path =
          absl::StrCat(fleet_dir, "/", SegmentName(segment->first));
      const int fd =
          ::open(path.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0644);
      if (fd < 0) return IoError(errno, absl::StrCat("create '", path, "'"));
      const File out(fd);
      absl::StatusOr<std::unique_ptr<File>> in = OpenForReads(segment->path);
      if (!in.ok()) return in.status();
      for (uint64_t at = 0; at < end; at += kCopyChunk) {
        absl::StatusOr<std::string> chunk = ReadAt(
            (*in)->fd, at,
            static_cast<size_t>(std::min<uint64_t>(kCopyChunk, end - at)),
            segment->path);
        if (!chunk.ok()) return chunk.status();
        if (absl::Status written = WriteAll(fd, *chunk, at, path);
            !written.ok()) {
          return written;
        }
      }
      if (::fdatasync(fd) != 0) {
        return IoError(errno, absl::StrCat("fdatasync '", path, "'"));
      }
    }
    if (absl::Status synced = SyncDirectory(fleet_dir); !synced.ok()) {
      return synced;
    }
  }
  return SyncDirectory(directory);
}

}  // namespace fleetmem::storage
