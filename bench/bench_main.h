// The main() of the Google Benchmark programs, in the help style of every
// fleetmem program (services/common/usage.h): --help and --version answered
// before any benchmark runs, an unknown flag a usage error (exit 2).
#ifndef FLEETMEM_BENCH_BENCH_MAIN_H_
#define FLEETMEM_BENCH_BENCH_MAIN_H_

#include <functional>
#include <string_view>

namespace fleetmem::bench {

// Runs the registered benchmarks; `before` (if any) runs first, after the
// command line was accepted.
int Main(int argc, char** argv, std::string_view program,
         std::string_view description,
         const std::function<void()>& before = {});

}  // namespace fleetmem::bench

#endif  // FLEETMEM_BENCH_BENCH_MAIN_H_
