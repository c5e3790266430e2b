#include "services/observability/process_stats.h"

#include <malloc.h>
#include <sys/resource.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace fleetmem::observability {
namespace {

absl::StatusOr<std::string> ReadText(const char* path) {
  std::ifstream in(path);
  if (!in) return absl::UnavailableError(absl::StrCat(path, ": cannot read"));
  std::ostringstream text;
  text << in.rdbuf();
  return text.str();
}

}  // namespace

absl::StatusOr<ProcessStats> ReadProcessStats() {
  absl::StatusOr<std::string> stat = ReadText("/proc/self/stat");
  if (!stat.ok()) return stat.status();
  // "pid (comm) state ppid ...": comm may hold spaces and parentheses, so
  // the fields are counted from after its last ')'; field 3 is state.
  const size_t close = stat->rfind(')');
  if (close == std::string::npos) {
    return absl::UnavailableError("/proc/self/stat: no command field");
  }
  const std::vector<std::string> fields =
      absl::StrSplit(stat->substr(close + 2), ' ', absl::SkipEmpty());
  // Fields 14, 15 (utime, stime), 22 (starttime), 23 (vsize), 24 (rss) of
  // proc(5), counted from 3 at fields[0].
  auto field = [&fields](size_t number, double* out) {
    return number - 3 < fields.size() &&
           absl::SimpleAtod(fields[number - 3], out);
  };
  double utime = 0, stime = 0, start_ticks = 0, vsize = 0, rss_pages = 0;
  if (!field(14, &utime) || !field(15, &stime) || !field(22, &start_ticks) ||
      !field(23, &vsize) || !field(24, &rss_pages)) {
    return absl::UnavailableError("/proc/self/stat: unexpected format");
  }
  const double ticks = static_cast<double>(sysconf(_SC_CLK_TCK));
  const double page = static_cast<double>(sysconf(_SC_PAGESIZE));
  ProcessStats out;
  out.cpu_seconds = (utime + stime) / ticks;
  out.virtual_bytes = vsize;
  out.resident_bytes = rss_pages * page;

  absl::StatusOr<std::string> system = ReadText("/proc/stat");
  if (!system.ok()) return system.status();
  double boot = -1;
  for (absl::string_view line : absl::StrSplit(*system, '\n')) {
    if (absl::ConsumePrefix(&line, "btime ") && absl::SimpleAtod(line, &boot)) {
      break;
    }
  }
  if (boot < 0) return absl::UnavailableError("/proc/stat: no btime line");
  out.start_time_seconds = boot + start_ticks / ticks;

  std::error_code error;
  for (std::filesystem::directory_iterator it("/proc/self/fd", error), end;
       !error && it != end; it.increment(error)) {
    out.open_fds += 1;
  }
  if (error) {
    return absl::UnavailableError(
        absl::StrCat("/proc/self/fd: ", error.message()));
  }
  rlimit limit{};
  if (getrlimit(RLIMIT_NOFILE, &limit) == 0) {
    out.max_fds = static_cast<double>(limit.rlim_cur);
  }
  return out;
}

HeapStats ReadHeapStats() {
  HeapStats out;
#if defined(__GLIBC__)
  // Sums over every arena (glibc 2.33+; bookworm has 2.36). uordblks and
  // fordblks count the arenas' blocks; hblkhd the separately mmapped ones.
  const struct mallinfo2 info = mallinfo2();
  out.in_use_bytes = static_cast<double>(info.uordblks + info.hblkhd);
  out.free_bytes = static_cast<double>(info.fordblks);
  out.mmapped_bytes = static_cast<double>(info.hblkhd);
#endif
  return out;
}

void TrimHeap() {
#if defined(__GLIBC__)
  malloc_trim(0);
#endif
}

}  // namespace fleetmem::observability
