#!/usr/bin/env bash
# Runs every libFuzzer harness of a fuzz build for SECONDS each, starting
# from its seed corpus in the tree (copied: the tree's corpus is not
# changed). Prints one summary line per fuzzer; exits 1 if any fuzzer found
# a crash, leak or timeout (its reproducer stays under BUILD/fuzz/artifacts).
#
#   tools/fuzz/run_fuzzers.sh build-asan 30
set -euo pipefail
build=${1:-build-asan}
seconds=${2:-30}
list="$build/fuzz/fuzzers.txt"
[ -s "$list" ] || { echo "run_fuzzers: no $list (configure with -DFLEETMEM_BUILD_FUZZ=ON)" >&2; exit 2; }
mkdir -p "$build/fuzz/artifacts" "$build/fuzz/logs"
failed=0
printf '%-22s %10s %8s %8s %s\n' fuzzer executions cov ft result
while read -r name seeds; do
  corpus="$build/fuzz/corpus/$name"
  mkdir -p "$corpus"
  log="$build/fuzz/logs/$name.log"
  if "$build/fuzz/$name" -max_total_time="$seconds" -rss_limit_mb=2048 \
       -max_len=65536 -timeout=10 -print_final_stats=1 \
       -artifact_prefix="$build/fuzz/artifacts/$name-" \
       "$corpus" "$seeds" >"$log" 2>&1; then
    result=clean
  else
    result="FOUND A PROBLEM (see $log)"
    failed=1
  fi
  execs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo '?')
  cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | grep -o '[0-9]*' || echo '?')
  ft=$(grep -o 'ft: [0-9]*' "$log" | tail -1 | grep -o '[0-9]*' || echo '?')
  printf '%-22s %10s %8s %8s %s\n' "$name" "$execs" "$cov" "$ft" "$result"
done <"$list"
exit $failed
