#!/bin/bash
# Where a restart's time goes (issue 49: restart to a served port <= 2 s at
# 1,000,000): the restart benchmark's fleet of N 256-d traces is filled
# (fill_scale_fleet), its place graph built and saved by a clean stop; then
# the server is started again under `perf record -e cpu-clock` until its
# port answers, and the engine's load lines, the time to the port and the
# samples by symbol (share of the whole start) are printed.
#
#   bench/restart_profile.sh [BUILD_DIR] [N]
#   (default: build 1000000)
# Environment: SERVER_BUILD (the server of another build; the load
# generator stays BUILD_DIR's), HNSW_CODES, HNSW_FLOATS (as
# bench/compare_rss.sh), TOP (30 symbols), KEEP (a directory: the filled
# data dir is kept there and reused by the next run with the same KEEP,
# which then skips the fill), DWARF=1 (call graphs unwound from DWARF,
# at 499 Hz: the symbols are then also printed with what they call
# included, so that a copy inlined into a caller shows with its page
# faults).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
n=${2:-1000000}
server_build=${SERVER_BUILD:-$build}
command -v perf >/dev/null || { echo "perf not found (apt-get install linux-perf)" >&2; exit 2; }
source "$here/tools/load/server_lib.sh"
bench_work restart-profile
work=$WORK
fill_scale_fleet_once "$server_build" "$work" "$n"

graph="-F 999 -g"
[ -n "${DWARF:-}" ] && graph="-F 499 --call-graph dwarf,8192"
start=$(date +%s.%N)
SERVER_START_SECONDS=1200 \
  SERVER_WRAPPER="perf record -q -e cpu-clock $graph -o $work/perf.data --" \
  start_server "$server_build" "$work/data" "$work/restart.log" \
  --config "$work/restart.textproto"
echo "port_seconds,$(awk "BEGIN { printf \"%.2f\", $(date +%s.%N) - $start }")"
kill -TERM "$(pgrep -P "$SERVER_PID" -f fleetmem-server)"
wait "$SERVER_PID" 2>/dev/null || true
grep -o 'fleet "scale": \(read [0-9]* trace records\|[0-9]* traces in [0-9]* clusters taken\|loaded from\|rebuilding\|index snapshot reconciled\).*' \
  "$work/restart.log" || true
grep -o 'fleet "scale" loaded.*' "$work/restart.log"
echo "# by symbol (share of the samples from start to stop; the stop is a"
echo "# small tail: no snapshot is written when nothing changed)"
perf report -i "$work/perf.data" --no-children --sort symbol --stdio \
  -g none 2>/dev/null | grep -v '^#' | grep '%' | sed 's/  */ /g' |
  head -"${TOP:-30}" || true  # head closes the pipe early: not a failure
if [ -n "${DWARF:-}" ]; then
  echo "# with what each calls included (inlined frames too)"
  perf report -i "$work/perf.data" --children --sort symbol --stdio \
    -g none 2>/dev/null | grep -v '^#' | grep '%' | sed 's/  */ /g' |
    head -"${TOP:-30}" || true
fi
