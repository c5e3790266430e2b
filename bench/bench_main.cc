#include "bench/bench_main.h"

#include <iostream>
#include <string>

#include "benchmark/benchmark.h"
#include "services/common/usage.h"

namespace fleetmem::bench {

int Main(int argc, char** argv, std::string_view program,
         std::string_view description, const std::function<void()>& before) {
  for (int i = 1; i < argc; ++i) {
    const std::string_view arg = argv[i];
    if (arg == "--version") {
      std::cout << common::VersionLine(program);
      return 0;
    }
    if (arg == "--help" || arg == "-h") {
      common::UsageText text;
      text.description = std::string(program) + ": " + std::string(description);
      text.usage = {std::string(program) + " [OPTIONS]"};
      text.sections.push_back(
          {"Options (Google Benchmark's)",
           {{"--benchmark_filter=REGEX", "run only the benchmarks it matches"},
            {"--benchmark_list_tests", "list the benchmarks and exit"},
            {"--benchmark_min_time=SECONDS", "time of each benchmark"},
            {"--benchmark_repetitions=N", "runs of each benchmark"},
            {"--benchmark_format=console|json|csv", "the report's format"},
            {"--benchmark_out=FILE", "also write the report to FILE"},
            {"--benchmark_out_format=json|console|csv", "FILE's format"},
            {"-h, --help", "print this help and exit"},
            {"--version", "print the version and exit"}}});
      text.footer = common::ExitStatusFooter();
      std::cout << common::FormatUsage(text);
      return 0;
    }
  }
  benchmark::Initialize(&argc, argv);
  if (argc > 1) {  // what Google Benchmark did not take
    std::cerr << common::UsageErrorText(
        program, std::string("unknown option '") + argv[1] + "'");
    return common::kExitUsage;
  }
  if (before) before();
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}

}  // namespace fleetmem::bench
