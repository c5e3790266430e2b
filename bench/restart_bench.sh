#!/bin/bash
# Restart at 1,000,000 traces without the long fill through the graph: one
# fleet of 256-d traces (4 robots, batches of 200) is filled on the exact
# index (`index: "exact"`; it prints the fill rate), then the server is
# stopped and started three times on the same data with the default
# (tiered) index; each start is timed until the port answers, with the
# engine's load line and the RSS right after it.
#
#   bench/restart_bench.sh [BUILD_DIR] [TRACES]   (default: build 1000000)
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
traces=${2:-1000000}
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
limits="memory { max_clusters: $((traces / 10 + 100)) }
limits { max_traces_per_fleet: $((traces * 2)) }"
printf 'index: "exact"\n%s\n' "$limits" >"$work/fill.textproto"
printf '%s\n' "$limits" >"$work/restart.textproto"
start_server "$build" "$work/data" "$work/fill.log" --config "$work/fill.textproto"
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet scale \
  --dimension 256 --robots 4 --batch 200 --seconds 100000 --traces "$traces" |
  tail -1
stop_server
for run in 1 2 3; do
  start=$(date +%s.%N)
  start_server "$build" "$work/data" "$work/restart.log" \
    --config "$work/restart.textproto"
  end=$(date +%s.%N)
  echo "restart_seconds,$(awk "BEGIN { printf \"%.2f\", $end - $start }")"
  grep -o 'fleet "scale" loaded.*' "$work/restart.log"
  echo "rss_mib_after_load,$(( $(ps -o rss= -p "$SERVER_PID") / 1024 ))"
  stop_server
done
