#include "services/common/cli_program.h"

#include <iostream>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_replace.h"

namespace fleetmem::common {
namespace {

// "--name TEXT", "-h, --help".
std::string ItemName(const CLI::Option& option) {
  std::string name =
      absl::StrReplaceAll(option.get_name(false, true), {{",", ", "}});
  if (option.get_type_size() != 0) {
    absl::StrAppend(&name, " ", option.get_type_name());
    if (option.get_expected_max() > 1) absl::StrAppend(&name, " ...");
  }
  return name;
}

std::string ItemHelp(const CLI::Option& option) {
  std::string help = option.get_description();
  if (option.get_required()) absl::StrAppend(&help, " (required)");
  const std::string fallback = option.get_default_str();
  if (option.get_type_size() != 0 && !fallback.empty()) {
    absl::StrAppend(&help, " (default: ", fallback, ")");
  }
  return help;
}

}  // namespace

std::string UsageFormatter::make_help(const CLI::App* app, std::string name,
                                      CLI::AppFormatMode mode) const {
  UsageText text;
  text.description = app->get_description();
  std::vector<const CLI::App*> commands = app->get_subcommands(
      [](const CLI::App* sub) { return !sub->get_name().empty(); });
  std::string usage = name;
  UsageSection arguments{"Arguments", {}};
  for (const CLI::Option* option : app->get_options(
           [](const CLI::Option* o) { return o->get_positional(); })) {
    absl::StrAppend(&usage, " ", option->get_name(true));
    arguments.items.push_back({option->get_name(true), ItemHelp(*option)});
  }
  if (!commands.empty()) absl::StrAppend(&usage, " COMMAND");
  absl::StrAppend(&usage, " [OPTIONS]");
  text.usage.push_back(usage);
  if (!commands.empty()) {
    text.usage.push_back(absl::StrCat(name, " COMMAND --help"));
  }
  text.sections.push_back(std::move(arguments));
  // Sections by the options' groups, in the order they appear.
  for (const CLI::Option* option : app->get_options(
           [](const CLI::Option* o) { return o->nonpositional(); })) {
    const std::string group =
        option->get_group().empty() ? "Options" : option->get_group();
    auto section =
        std::find_if(text.sections.begin(), text.sections.end(),
                     [&](const UsageSection& s) { return s.title == group; });
    if (section == text.sections.end()) {
      text.sections.push_back({group, {}});
      section = text.sections.end() - 1;
    }
    section->items.push_back({ItemName(*option), ItemHelp(*option)});
  }
  UsageSection command_section{"Commands", {}};
  for (const CLI::App* command : commands) {
    command_section.items.push_back(
        {command->get_name(), command->get_description()});
  }
  text.sections.push_back(std::move(command_section));
  text.footer = app->get_footer();
  return FormatUsage(text);
}

void SetUpProgram(CLI::App& app, std::string_view program) {
  app.name(std::string(program));
  app.formatter(std::make_shared<UsageFormatter>());
  app.set_help_flag("-h,--help", "print this help and exit");
  std::string version = VersionLine(program);
  version.pop_back();  // CLI11 prints its own newline
  app.set_version_flag("--version", version, "print the version and exit");
  app.footer(ExitStatusFooter());
}

std::optional<int> ParseProgram(CLI::App& app, int argc, char** argv) {
  try {
    app.parse(argc, argv);
    return std::nullopt;
  } catch (const CLI::ParseError& error) {
    if (error.get_exit_code() == 0) return app.exit(error);  // help, version
    // The program's name (`app` is the program, not a subcommand).
    std::cerr << UsageErrorText(app.get_name(), error.what());
    return kExitUsage;
  }
}

}  // namespace fleetmem::common
