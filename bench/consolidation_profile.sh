#!/bin/bash
# Where a full memory's consolidations go (issue 49: consolidation with
# forgetting < 20 ms at 10,000,000): the restart benchmark's fleet of N
# 256-d traces is filled (fill_scale_fleet_once), the server started on a
# copy of it and, once its graph holds every code, K_max is lowered to the
# clusters held; then one robot uploads CONSOLIDATE_TRACES (20,000) traces
# in segments of 200 (every consolidation forgets 20 clusters by merging)
# while `perf record -e cpu-clock -g` samples the server. Prints the mean
# consolidation time (the server's histogram) and the samples by thread,
# by symbol and by symbol in the applier's thread alone (shares of all the
# server's samples while the traces were applied).
#
#   bench/consolidation_profile.sh [BUILD_DIR] [N]
#   (default: build 1000000)
# Environment: TOP (40 symbols), KEEP (a directory: the filled data dir is
# kept there and reused by the next run with the same KEEP).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
n=${2:-1000000}
traces=${CONSOLIDATE_TRACES:-20000}
command -v perf >/dev/null || { echo "perf not found (apt-get install linux-perf)" >&2; exit 2; }
source "$here/tools/load/server_lib.sh"
bench_work consolidation-profile data-profile
fill_scale_fleet_once "$build" "$WORK" "$n"
serve_fill_copy "$build" "$WORK" data-profile "$WORK/profile.log"
clusters=$("$build/bin/fleetmem" --server "$SERVER_ADDR" --json stats \
  --fleet scale | /usr/bin/python3 -c \
  'import json, sys; print(int(json.load(sys.stdin)["clusters"]))')
"$build/bin/fleetmem" --server "$SERVER_ADDR" update-fleet --fleet scale \
  --max-clusters "$clusters" >/dev/null
read -r sum0 count0 < <(consolidation_metric)
server=$(pgrep -P "$SERVER_PID" -f fleetmem-server || echo "$SERVER_PID")
perf record -q -e cpu-clock -F 999 -g -p "$server" -o "$WORK/perf.data" &
perf_pid=$!
sleep 1
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet scale \
  --dimension 256 --robots 1 --batch 200 --seconds 100000 \
  --first-seq 100000000 --traces "$traces" >/dev/null
while [ "$(backlog_traces "$build" scale)" -gt 0 ]; do sleep 0.2; done
kill -INT "$perf_pid"
wait "$perf_pid" 2>/dev/null || true
read -r sum1 count1 < <(consolidation_metric)
awk -v s0="$sum0" -v s1="$sum1" -v a="$count0" -v b="$count1" \
  'BEGIN { printf "consolidations,%d\nmean_ms,%.2f\n", b - a,
           (b > a ? 1000 * (s1 - s0) / (b - a) : 0) }'
kill -9 "$SERVER_PID"
wait "$SERVER_PID" 2>/dev/null || true
echo "# by thread"
perf_report "$WORK/perf.data" --sort comm
echo "# by symbol"
perf_report "$WORK/perf.data" --sort symbol
echo "# the applier's thread alone (shares of all the samples)"
perf_report "$WORK/perf.data" --sort symbol --comm fleetmem-apply
