// The one help layout of every fleetmem program (issue 48: three styles
// before). A help text is a description, a usage line and titled sections
// of items (a flag or a command beside its help), wrapped to 80 columns:
//
//   fleetmem-credential: makes a principal for fleetmem-server's --auth-file.
//
//   Usage: fleetmem-credential --name NAME --role ROLE [OPTIONS]
//
//   Options:
//     --name NAME               principal name, e.g. robot-7 (required)
//     --very-long-flag-name VALUE
//                               its help, on the next line
//
//   Exit status: 0 success, 1 failure (printed), 2 bad usage.
//
// Every program exits with kExitUsage after a usage error and prints
// "NAME: error: ...", then "Run 'NAME --help' for usage." on stderr.
#ifndef FLEETMEM_SERVICES_COMMON_USAGE_H_
#define FLEETMEM_SERVICES_COMMON_USAGE_H_

#include <string>
#include <string_view>
#include <vector>

namespace fleetmem::common {

inline constexpr int kExitUsage = 2;
inline constexpr size_t kUsageWidth = 80;   // columns of every line
inline constexpr size_t kUsageColumn = 28;  // where an item's help starts

struct UsageItem {
  std::string name;  // "--data-dir DIR", "-h, --help", "upload"
  std::string help;  // one paragraph, wrapped when printed
};

struct UsageSection {
  std::string title;  // "Options", "Commands", ...
  std::vector<UsageItem> items;
};

struct UsageText {
  std::string description;         // first paragraph
  std::vector<std::string> usage;  // one or more "Usage:" lines
  std::vector<UsageSection> sections;
  std::string footer;  // last paragraph (may be empty)
};

// The text, every line at most kUsageWidth columns (a word longer than a
// line is left whole).
std::string FormatUsage(const UsageText& text);

// `text` wrapped to `width` columns, every line after the first indented by
// `indent` spaces (the first is the caller's).
std::string Wrap(std::string_view text, size_t width, size_t indent = 0);

// The standard footer: what the exit codes mean.
std::string ExitStatusFooter();

// "NAME: error: MESSAGE\nRun 'NAME --help' for usage.\n"
std::string UsageErrorText(std::string_view program, std::string_view message);

// The line --version prints: "NAME VERSION\n".
std::string VersionLine(std::string_view program);

}  // namespace fleetmem::common

#endif  // FLEETMEM_SERVICES_COMMON_USAGE_H_
