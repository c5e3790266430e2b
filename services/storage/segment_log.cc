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
// O_DIRECT writes whole blocks at block offsets: each append ends with a
// padding record (sequence 0) to the next block.
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
  struct Record {
    uint64_t sequence, offset, size;
  };
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
};

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

absl::Status SegmentLog::LoadFleet(const std::string& fleet_id,
                                   const std::string& path) {
  Fleet& fleet = FindOrMake(fleet_id);
  absl::MutexLock lock(&fleet.mu);
  std::error_code error;
  std::vector<std::pair<uint64_t, std::string>> files;
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
      fleet.spares.push_back(entry.path().string());
      fleet.next_spare = std::max(fleet.next_spare, number + 1);
    } else {
      files.emplace_back(number, entry.path().string());
    }
  }
  if (error) {
    return absl::UnavailableError(
        absl::StrCat("list '", path, "': ", error.message()));
  }
  std::sort(files.begin(), files.end());
  // Sequences run on across segments: each segment starts right after the
  // last record before it.
  uint64_t last = 0;
  for (const auto& [first, file_path] : files) {
    if (last != 0 && first != last + 1) {
      FLEETMEM_LOG(kError)
          << "ingest log of fleet \"" << fleet_id << "\": segment '"
          << file_path << "' starts at entry " << first
          << " but the segments before it end at " << last
          << ": the entries between are lost (a segment damaged before its "
             "end)";
    }
    auto segment = std::make_shared<Segment>();
    segment->first = first;
    segment->path = file_path;
    absl::StatusOr<std::unique_ptr<File>> reader = OpenForReads(file_path);
    if (!reader.ok()) return reader.status();
    const int fd = (*reader)->fd;
    struct stat info;
    if (::fstat(fd, &info) != 0) {
      return IoError(errno, absl::StrCat("stat '", file_path, "'"));
    }
    const uint64_t size = static_cast<uint64_t>(info.st_size);
    uint64_t expected = first;
    while (segment->end + kHeaderBytes <= size) {
      absl::StatusOr<std::string> header =
          ReadAt(fd, segment->end, kHeaderBytes, file_path);
      if (!header.ok()) return header.status();
      const uint32_t payload = Load<uint32_t>(header->data() + 28);
      if (std::memcmp(header->data(), kMagic, sizeof(kMagic)) != 0 ||
          segment->end + kHeaderBytes + payload > size) {
        break;
      }
      absl::StatusOr<std::string> record =
          ReadAt(fd, segment->end, kHeaderBytes + payload, file_path);
      if (!record.ok()) return record.status();
      const uint64_t sequence = Load<uint64_t>(record->data() + 20);
      if (!Intact(*record, first, sequence == 0 ? 0 : expected)) break;
      if (sequence != 0) {
        segment->records.push_back({expected, segment->end, record->size()});
        ++expected;
      }
      segment->end += record->size();
    }
    last = segment->records.empty() ? first - 1 : segment->last();
    fleet.segments.push_back(std::move(segment));
  }
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

std::vector<SegmentLog::Fleet*> SegmentLog::Fleets() {
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

absl::Status SegmentLog::Append(std::string_view fleet_id,
                                std::span<const engine::LogAppend> entries) {
  if (entries.empty()) return absl::OkStatus();
  std::vector<LoggedUploadBytes> payloads;
  payloads.reserve(entries.size());
  uint64_t bytes = 0;
  for (const engine::LogAppend& entry : entries) {
    payloads.emplace_back(entry.traces);
    bytes += kHeaderBytes + payloads.back().size();
  }
  if (options_.check_room) {
    if (absl::Status room = options_.check_room(fleet_id, bytes); !room.ok()) {
      return room;
    }
  }
  Fleet& fleet = FindOrMake(fleet_id);
  std::shared_ptr<Segment> segment;
  uint64_t offset = 0;
  {
    absl::MutexLock lock(&fleet.mu);
    if (!fleet.segments.empty()) {
      const std::shared_ptr<Segment>& last = fleet.segments.back();
      // A segment's records run on from its first sequence.
      const uint64_t next =
          last->records.empty() ? last->first : last->last() + 1;
      if (!fleet.sealed && last->end < options_.segment_bytes &&
          next == entries.front().sequence) {
        segment = last;
        offset = last->end;
      } else if (last->records.empty() &&
                 last->first == entries.front().sequence) {
        // A failed first append left it empty: start it again.
        segment = last;
      }
    }
  }
  if (segment != nullptr && segment->file == nullptr) {
    // A segment found at Open: no descriptor for appends yet.
    if (absl::Status opened = OpenForAppends(*segment); !opened.ok()) {
      return absl::Status(opened.code(),
                          absl::StrCat("append to the ingest log of fleet \"",
                                       V(fleet_id), "\": ", opened.message(),
                                       " (nothing of it was stored)"));
    }
  }
  if (segment != nullptr) {
    absl::MutexLock lock(&fleet.mu);
    fleet.sealed = false;
  }
  const bool started = segment == nullptr;
  if (started) {
    absl::StatusOr<std::shared_ptr<Segment>> made =
        StartSegment(fleet, entries.front().sequence);
    if (!made.ok()) {
      return absl::Status(
          made.status().code(),
          absl::StrCat("append to the ingest log of fleet \"", V(fleet_id),
                       "\": ", made.status().message(),
                       " (nothing of it was stored)"));
    }
    segment = *std::move(made);
  }
  // Records, then (O_DIRECT) a padding record to the next block.
  size_t size = bytes;
  if (segment->direct) {
    size = RoundUp(bytes);
    if (size != bytes && size - bytes < kHeaderBytes) size += kBlock;
  }
  AlignedBuffer buffer = Allocate(size);
  if (buffer == nullptr) {
    return absl::ResourceExhaustedError(absl::StrCat(
        "no memory for an append of ", size, " bytes (nothing was stored)"));
  }
  std::vector<Segment::Record> records;
  size_t at = 0;
  for (size_t i = 0; i < entries.size(); ++i) {
    const LoggedUploadBytes& payload = payloads[i];
    records.push_back(
        {entries[i].sequence, offset + at, kHeaderBytes + payload.size()});
    payload.WriteTo(buffer.get() + at + kHeaderBytes);
    WriteHeader(buffer.get() + at, segment->first, entries[i].sequence,
                static_cast<uint32_t>(payload.size()));
    at += kHeaderBytes + payload.size();
  }
  if (size > at) {
    std::memset(buffer.get() + at, 0, size - at);
    WriteHeader(buffer.get() + at, segment->first, 0,
                static_cast<uint32_t>(size - at - kHeaderBytes));
  }
  const int fd = segment->file->fd;
  absl::Status written =
      WriteAll(fd, std::string_view(buffer.get(), size), offset, segment->path);
  if (written.ok() && ::fdatasync(fd) != 0) {
    written = IoError(errno, absl::StrCat("fdatasync '", segment->path, "'"));
  }
  if (!written.ok()) {
    // Undo: a zero block where the first record began ends the segment
    // there for readers after a restart. The next append starts another.
    std::memset(buffer.get(), 0, kBlock);
    const bool undone = WriteAll(fd, std::string_view(buffer.get(), kBlock),
                                 offset, segment->path)
                            .ok() &&
                        ::fdatasync(fd) == 0;
    {
      absl::MutexLock lock(&fleet.mu);
      fleet.sealed = true;
      if (started) fleet.segments.push_back(segment);
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
  if (started) {
    // The segment before takes no more appends: its descriptor goes.
    if (!fleet.segments.empty()) fleet.segments.back()->file.reset();
    fleet.segments.push_back(segment);
  }
  segment->end = offset + size;
  segment->records.insert(segment->records.end(), records.begin(),
                          records.end());
  return absl::OkStatus();
}

absl::StatusOr<std::vector<engine::LoggedUpload>> SegmentLog::Read(
    std::string_view fleet_id, uint64_t after, size_t max_entries) {
  std::vector<engine::LoggedUpload> out;
  Fleet* fleet = Find(fleet_id);
  if (fleet == nullptr || max_entries == 0) return out;
  struct Wanted {
    std::shared_ptr<const Segment> segment;
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
      return absl::DataLossError(
          absl::StrCat(where, " fails its checksum or frame"));
    }
    absl::StatusOr<std::vector<core::MemoryTrace>> traces = DecodeLoggedTraces(
        where, std::string_view(*record).substr(kHeaderBytes));
    if (!traces.ok()) return traces.status();
    out.push_back({want.sequence, *std::move(traces)});
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

std::vector<std::pair<std::string, uint64_t>> SegmentLog::Tails() {
  const std::vector<Fleet*> fleets = Fleets();
  std::vector<std::pair<std::string, uint64_t>> tails;
  for (Fleet* fleet : fleets) {
    absl::MutexLock lock(&fleet->mu);
    for (auto it = fleet->segments.rbegin(); it != fleet->segments.rend();
         ++it) {
      if (!(*it)->records.empty()) {
        tails.emplace_back(fleet->id, (*it)->last());
        break;
      }
    }
  }
  return tails;
}

uint64_t SegmentLog::Bytes() {
  const std::vector<Fleet*> fleets = Fleets();
  uint64_t bytes = 0;
  for (Fleet* fleet : fleets) {
    absl::MutexLock lock(&fleet->mu);
    for (const std::shared_ptr<Segment>& segment : fleet->segments) {
      bytes += segment->end;
    }
  }
  return bytes;
}

absl::Status SegmentLog::CopyTo(const std::string& directory,
                                const std::function<absl::Status()>& first) {
  absl::MutexLock trims(&trim_mu_);
  if (first) {
    if (absl::Status done = first(); !done.ok()) return done;
  }
  if (absl::Status made = MakeDirectory(directory); !made.ok()) return made;
  const std::vector<Fleet*> fleets = Fleets();
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
