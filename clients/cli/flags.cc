#include "clients/cli/flags.h"

#include <algorithm>
#include <cmath>
#include <optional>
#include <utility>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "services/common/usage.h"

namespace fleetmem::cli {
namespace {

const FlagSpec* FindFlag(std::span<const FlagSpec> flags,
                         absl::string_view name) {
  for (const FlagSpec& flag : flags) {
    if (flag.name == name) return &flag;
  }
  return nullptr;
}

const CommandSpec* FindCommand(std::span<const CommandSpec> commands,
                               absl::string_view name) {
  for (const CommandSpec& command : commands) {
    if (command.name == name) return &command;
  }
  return nullptr;
}

// The flags as help items ("--name VALUE", help).
common::UsageSection FlagSection(std::string title,
                                 std::span<const FlagSpec> flags) {
  common::UsageSection section{std::move(title), {}};
  for (const FlagSpec& flag : flags) {
    section.items.push_back(
        {flag.value_name.empty()
             ? absl::StrCat("--", flag.name)
             : absl::StrCat("--", flag.name, " ", flag.value_name),
         flag.help});
  }
  return section;
}

}  // namespace

void FlagValues::Set(absl::string_view name, std::string value) {
  values_[std::string(name)] = std::move(value);
}

bool FlagValues::Has(absl::string_view name) const {
  return values_.find(name) != values_.end();
}

absl::StatusOr<std::string> FlagValues::Required(absl::string_view name) const {
  auto it = values_.find(name);
  if (it == values_.end() || it->second.empty()) {
    return absl::InvalidArgumentError(absl::StrCat("--", name, " is required"));
  }
  return it->second;
}

std::string FlagValues::StringOr(absl::string_view name,
                                 std::string fallback) const {
  auto it = values_.find(name);
  return it == values_.end() ? fallback : it->second;
}

absl::StatusOr<uint64_t> FlagValues::UintOr(absl::string_view name,
                                            uint64_t fallback,
                                            uint64_t max) const {
  if (!Has(name)) return fallback;
  return RequiredUint(name, max);
}

absl::StatusOr<uint64_t> FlagValues::RequiredUint(absl::string_view name,
                                                  uint64_t max) const {
  absl::StatusOr<std::string> text = Required(name);
  if (!text.ok()) return text.status();
  uint64_t value = 0;
  if (!absl::SimpleAtoi(*text, &value) || value > max) {
    return absl::InvalidArgumentError(absl::StrCat(
        "--", name, " wants an integer in 0..", max, ", not '", *text, "'"));
  }
  return value;
}

absl::StatusOr<double> FlagValues::RequiredDouble(
    absl::string_view name) const {
  absl::StatusOr<std::string> text = Required(name);
  if (!text.ok()) return text.status();
  double value = 0;
  if (!absl::SimpleAtod(*text, &value) || !std::isfinite(value)) {
    return absl::InvalidArgumentError(
        absl::StrCat("--", name, " wants a number, not '", *text, "'"));
  }
  return value;
}

absl::StatusOr<std::vector<double>> FlagValues::RequiredList(
    absl::string_view name) const {
  absl::StatusOr<std::string> text = Required(name);
  if (!text.ok()) return text.status();
  return ParseNumberList(*text, absl::StrCat("--", name));
}

absl::StatusOr<std::vector<double>> ParseNumberList(absl::string_view text,
                                                    absl::string_view what) {
  std::vector<double> numbers;
  for (absl::string_view word :
       absl::StrSplit(text, absl::ByAnyChar(", \t\n\r"), absl::SkipEmpty())) {
    double value = 0;
    if (!absl::SimpleAtod(word, &value) || !std::isfinite(value)) {
      return absl::InvalidArgumentError(
          absl::StrCat(what, ": '", word, "' is not a finite number"));
    }
    numbers.push_back(value);
  }
  if (numbers.empty()) {
    return absl::InvalidArgumentError(absl::StrCat(what, ": no numbers"));
  }
  return numbers;
}

absl::StatusOr<CommandLine> ParseCommandLine(
    std::span<const std::string> args, std::span<const FlagSpec> global_flags,
    std::span<const CommandSpec> commands) {
  CommandLine line;
  const CommandSpec* command = nullptr;
  for (size_t i = 0; i < args.size(); ++i) {
    absl::string_view arg = args[i];
    if (arg == "--help" || arg == "-h") {
      line.help = true;
      continue;
    }
    if (!absl::ConsumePrefix(&arg, "--")) {
      if (command == nullptr) {
        command = FindCommand(commands, arg);
        if (command == nullptr) {
          return absl::InvalidArgumentError(
              absl::StrCat("unknown command '", arg, "'"));
        }
        line.command = command->name;
      } else {
        line.positional.emplace_back(arg);
      }
      continue;
    }
    absl::string_view name = arg;
    std::optional<std::string> value;
    if (size_t equals = arg.find('='); equals != absl::string_view::npos) {
      name = arg.substr(0, equals);
      value = std::string(arg.substr(equals + 1));
    }
    FlagValues* target = &line.global;
    const FlagSpec* flag = FindFlag(global_flags, name);
    if (flag == nullptr && command != nullptr) {
      flag = FindFlag(command->flags, name);
      target = &line.flags;
    }
    if (flag == nullptr) {
      return absl::InvalidArgumentError(
          command == nullptr ? absl::StrCat("unknown flag --", name)
                             : absl::StrCat("unknown flag --", name, " for '",
                                            command->name, "'"));
    }
    if (flag->value_name.empty()) {
      if (value.has_value()) {
        return absl::InvalidArgumentError(
            absl::StrCat("--", name, " takes no value"));
      }
      value = "true";
    } else if (!value.has_value()) {
      if (i + 1 >= args.size()) {
        return absl::InvalidArgumentError(absl::StrCat(
            "--", name, " needs a value (", flag->value_name, ")"));
      }
      value = args[++i];
    }
    target->Set(name, *std::move(value));
  }
  return line;
}

std::string FormatToolHelp(std::span<const FlagSpec> global_flags,
                           std::span<const CommandSpec> commands) {
  common::UsageText text;
  text.description =
      "fleetmem: command-line client of a fleetmem server (one shared memory "
      "per robot fleet).";
  text.usage = {"fleetmem [GLOBAL OPTIONS] COMMAND [OPTIONS]",
                "fleetmem COMMAND --help", "fleetmem --version"};
  common::UsageSection listed{"Commands", {}};
  for (const CommandSpec& command : commands) {
    listed.items.push_back({command.name, command.summary});
  }
  text.sections.push_back(std::move(listed));
  text.sections.push_back(FlagSection("Global options", global_flags));
  text.footer =
      "Exit status: 0 success, 1 failure (the server's error printed as "
      "\"error: CODE: message\"), 2 bad usage or input.";
  return common::FormatUsage(text);
}

std::string FormatCommandHelp(const CommandSpec& command,
                              std::span<const FlagSpec> global_flags) {
  common::UsageText text;
  text.description = command.summary;
  if (!command.description.empty()) {
    absl::StrAppend(&text.description, "\n\n", command.description);
  }
  text.usage = {absl::StrCat("fleetmem ", command.name,
                             command.synopsis.empty() ? "" : " ",
                             command.synopsis)};
  text.sections.push_back(FlagSection("Options", command.flags));
  text.sections.push_back(FlagSection("Global options", global_flags));
  return common::FormatUsage(text);
}

}  // namespace fleetmem::cli
