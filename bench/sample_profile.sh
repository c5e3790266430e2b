#!/bin/bash
# Where a SampleReplay's time goes (issue 49: SampleReplay of 1,000 < 2 ms,
# flat from 5,000): the restart benchmark's fleet of N 256-d traces is
# filled (fill_scale_fleet_once), the server started on a copy of it and,
# once its graph holds every code, the load generator draws RATE
# SampleReplay calls of 1,000 a second for SECONDS (no queries, no
# uploads; its bare gRPC peer answers the same calls after it) while
# `perf record -e cpu-clock -g` samples the server. Prints the load
# generator's row for both (sample p50/p99) and the server's samples by
# thread, by symbol and by symbol in the applier's thread alone (a draw
# is a logged call: the applier draws it and writes the replay counts).
#
#   bench/sample_profile.sh [BUILD_DIR] [N]
#   (default: build 1000000)
# Environment: SAMPLE_SECONDS (20), SAMPLE_RATE (20), TOP (40), KEEP (a
# directory: the filled data dir is kept there and reused by the next run
# with the same KEEP).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
n=${2:-1000000}
command -v perf >/dev/null || { echo "perf not found (apt-get install linux-perf)" >&2; exit 2; }
source "$here/tools/load/server_lib.sh"
bench_work sample-profile data-profile
fill_scale_fleet_once "$build" "$WORK" "$n"
serve_fill_copy "$build" "$WORK" data-profile "$WORK/profile.log"
perf record -q -e cpu-clock -F 999 -g -p "$SERVER_PID" -o "$WORK/perf.data" &
perf_pid=$!
sleep 1
"$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet scale \
  --dimension 256 --robots 0 --seconds "${SAMPLE_SECONDS:-20}" \
  --query-rate 0 --sample-rate "${SAMPLE_RATE:-20}" \
  --csv "$WORK/calls.csv" >/dev/null 2>&1
kill -INT "$perf_pid"
wait "$perf_pid" 2>/dev/null || true
kill -9 "$SERVER_PID"
wait "$SERVER_PID" 2>/dev/null || true
cut -d, -f1,15-17 "$WORK/calls.csv"
echo "# by thread (the server's samples while the load generator drew)"
perf_report "$WORK/perf.data" --sort comm
echo "# by symbol"
perf_report "$WORK/perf.data" --sort symbol
echo "# the applier's thread alone (shares of all the samples)"
perf_report "$WORK/perf.data" --sort symbol --comm fleetmem-apply
