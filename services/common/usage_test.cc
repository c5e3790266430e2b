#include "services/common/usage.h"

#include <sstream>
#include <string>
#include <vector>

#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "services/common/cli_program.h"

namespace fleetmem::common {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

void ExpectNarrow(const std::string& text) {
  for (absl::string_view line : absl::StrSplit(text, '\n')) {
    EXPECT_LE(line.size(), kUsageWidth) << line;
  }
}

TEST(FormatUsageTest, ItemsWrapBesideTheirNamesAndLongNamesStandAlone) {
  UsageText text;
  text.description = "prog: does one thing.";
  text.usage = {"prog --data-dir DIR [OPTIONS]"};
  text.sections.push_back(
      {"Options",
       {{"--data-dir DIR", std::string(30, 'a') + " " + std::string(30, 'b') +
                               " " + std::string(30, 'c')},
        {"--a-very-long-flag-name-indeed VALUE", "short help"}}});
  text.footer = ExitStatusFooter();
  const std::string help = FormatUsage(text);
  ExpectNarrow(help);
  EXPECT_THAT(help, HasSubstr("Usage: prog --data-dir DIR [OPTIONS]\n"));
  // The help's lines all start in one column.
  EXPECT_THAT(help,
              HasSubstr("  --data-dir DIR" + std::string(12, ' ') +
                        std::string(30, 'a') + "\n" +
                        std::string(kUsageColumn, ' ') + std::string(30, 'b')));
  EXPECT_THAT(help, HasSubstr("  --a-very-long-flag-name-indeed VALUE\n" +
                              std::string(kUsageColumn, ' ') + "short help"));
  EXPECT_THAT(help, HasSubstr("Exit status: 0 success"));
}

TEST(CliProgramTest, HelpNamesTheProgramAndListsHelpVersionAndDefaults) {
  CLI::App app{"tool: makes things."};
  SetUpProgram(app, "fleetmem-tool");
  std::string name;
  int count = 3;
  app.add_option("--name", name, "what to make")->required();
  app.add_option("--count", count, "how many")->capture_default_str();
  CLI::App* sub = app.add_subcommand("again", "makes them again");
  int times = 1;
  sub->add_option("--times", times, "how often");
  const std::string help = app.help();
  ExpectNarrow(help);
  EXPECT_THAT(help, HasSubstr("Usage: fleetmem-tool COMMAND [OPTIONS]"));
  EXPECT_THAT(help, HasSubstr("-h, --help"));
  EXPECT_THAT(help, HasSubstr("--version"));
  EXPECT_THAT(help, HasSubstr("what to make (required)"));
  EXPECT_THAT(help, HasSubstr("how many (default: 3)"));
  EXPECT_THAT(help, HasSubstr("again"));
  const std::string sub_help = sub->help("fleetmem-tool");
  EXPECT_THAT(sub_help, HasSubstr("Usage: fleetmem-tool again [OPTIONS]"));
  EXPECT_THAT(sub_help, HasSubstr("--times INT"));
}

TEST(CliProgramTest, UsageErrorsExitTwoAndHelpAndVersionZero) {
  auto parse = [](std::vector<std::string> words, std::string* err) {
    CLI::App app{"tool"};
    SetUpProgram(app, "fleetmem-tool");
    std::string name;
    app.add_option("--name", name, "what")->required();
    std::vector<char*> argv;
    for (std::string& word : words) argv.push_back(word.data());
    std::ostringstream captured;
    std::streambuf* old = std::cerr.rdbuf(captured.rdbuf());
    std::streambuf* old_out = std::cout.rdbuf(captured.rdbuf());
    std::optional<int> code =
        ParseProgram(app, static_cast<int>(argv.size()), argv.data());
    std::cerr.rdbuf(old);
    std::cout.rdbuf(old_out);
    *err = captured.str();
    return code;
  };
  std::string err;
  EXPECT_EQ(parse({"/build/bin/fleetmem-tool"}, &err), kExitUsage);
  EXPECT_THAT(err, HasSubstr("fleetmem-tool: error: --name is required"));
  EXPECT_THAT(err, Not(HasSubstr("/build/")));
  EXPECT_EQ(parse({"x", "--name", "a", "--bogus"}, &err), kExitUsage);
  EXPECT_EQ(parse({"x", "--version"}, &err), 0);
  EXPECT_EQ(err, VersionLine("fleetmem-tool"));
  EXPECT_EQ(parse({"x", "--help"}, &err), 0);
  EXPECT_THAT(err, HasSubstr("Usage: fleetmem-tool [OPTIONS]"));
  EXPECT_EQ(parse({"x", "--name", "a"}, &err), std::nullopt);
}

}  // namespace
}  // namespace fleetmem::common
