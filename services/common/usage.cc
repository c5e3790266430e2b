#include "services/common/usage.h"

#include <algorithm>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "fleetmem_version.h"

namespace fleetmem::common {
namespace {

// Debian's Abseil has its own string_view (services/core/absl_view.h).
absl::string_view A(std::string_view s) { return {s.data(), s.size()}; }

}  // namespace

std::string Wrap(std::string_view text, size_t width, size_t indent) {
  std::string out;
  size_t column = 0;  // of the line being written, after its indent
  const size_t room = width > indent ? width - indent : 1;
  for (absl::string_view word :
       absl::StrSplit(A(text), ' ', absl::SkipEmpty())) {
    if (column > 0 && column + 1 + word.size() > room) {
      absl::StrAppend(&out, "\n", std::string(indent, ' '));
      column = 0;
    } else if (column > 0) {
      out += ' ';
      ++column;
    }
    absl::StrAppend(&out, word);
    column += word.size();
  }
  return out;
}

std::string FormatUsage(const UsageText& text) {
  std::string out;
  // Paragraphs of the description and the footer keep their breaks; an
  // indented line is preformatted (an example) and kept as it is.
  auto paragraphs = [&out](std::string_view block) {
    for (absl::string_view line : absl::StrSplit(A(block), '\n')) {
      if (absl::StartsWith(line, " ") || line.size() <= kUsageWidth) {
        absl::StrAppend(&out, line, "\n");
      } else {
        absl::StrAppend(&out, Wrap({line.data(), line.size()}, kUsageWidth),
                        "\n");
      }
    }
  };
  if (!text.description.empty()) {
    paragraphs(text.description);
    out += "\n";
  }
  for (size_t i = 0; i < text.usage.size(); ++i) {
    const std::string head = i == 0 ? "Usage: " : "       ";
    absl::StrAppend(
        &out, head,
        Wrap(text.usage[i], kUsageWidth - head.size(), head.size() + 2), "\n");
  }
  for (const UsageSection& section : text.sections) {
    if (section.items.empty()) continue;
    absl::StrAppend(&out, "\n", section.title, ":\n");
    for (const UsageItem& item : section.items) {
      std::string line = absl::StrCat("  ", item.name);
      if (item.help.empty()) {
        absl::StrAppend(&out, line, "\n");
        continue;
      }
      if (line.size() + 2 > kUsageColumn) {
        absl::StrAppend(&out, line, "\n");
        line.clear();
      }
      line.resize(kUsageColumn, ' ');
      absl::StrAppend(&out, line, Wrap(item.help, kUsageWidth, kUsageColumn),
                      "\n");
    }
  }
  if (!text.footer.empty()) {
    out += "\n";
    paragraphs(text.footer);
  }
  return out;
}

std::string ExitStatusFooter() {
  return "Exit status: 0 success, 1 failure (the reason printed), 2 bad "
         "usage.";
}

std::string UsageErrorText(std::string_view program, std::string_view message) {
  return absl::StrCat(A(program), ": error: ", A(message), "\nRun '",
                      A(program), " --help' for usage.\n");
}

std::string VersionLine(std::string_view program) {
  return absl::StrCat(A(program), " ", FLEETMEM_VERSION, "\n");
}

}  // namespace fleetmem::common
