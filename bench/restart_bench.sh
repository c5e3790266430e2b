#!/bin/bash
# Restart at 1,000,000 traces, with and without the index snapshot a clean
# shutdown writes. One fleet of 256-d traces (4 robots, batches of 200) is
# filled on the exact index (`index: "exact"`; it prints the fill rate). The
# server is then started on the default (tiered) index, which rebuilds the
# HNSW graph in the background (the path after a crash: timed until GetStats
# shows no unindexed code), and stopped with SIGTERM, which saves the
# snapshot. Three restarts follow, each timed until the port answers, with
# the codes outside the graph at that moment, the median query over the
# next 5 s, the engine's load lines and the RSS. Last, a kill -9 and a
# restart: no snapshot, so the graph is rebuilt again.
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

seconds_since() { awk "BEGIN { printf \"%.2f\", $(date +%s.%N) - $1 }"; }

# restart LABEL: starts on the default index and prints what the load cost.
restart() {
  local start
  start=$(date +%s.%N)
  start_server "$build" "$work/data" "$work/restart.log" \
    --config "$work/restart.textproto"
  echo "$1_restart_seconds,$(seconds_since "$start")"
  echo "$1_unindexed_codes_at_open,$(unindexed_codes "$build" scale)"
  "$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet scale \
    --dimension 256 --robots 0 --seconds 5 --query-rate 20 \
    --csv "$work/calls.csv" >/dev/null 2>&1
  echo "$1_query_p50_ms_after_open,$(sed -n 2p "$work/calls.csv" | cut -d, -f13)"
  grep -o 'fleet "scale": \(loaded from\|rebuilding\|forgetting\).*' "$work/restart.log" || true
  grep -o 'fleet "scale" loaded.*' "$work/restart.log"
  echo "$1_rss_mib_after_load,$(( $(ps -o rss= -p "$SERVER_PID") / 1024 ))"
}

# stop_and_report: SIGTERM (the snapshot is written) and its size and time.
stop_and_report() {
  stop_server
  grep -o 'fleet "scale": index snapshot.*' "$work/restart.log"
  echo "snapshot_mib,$(( $(du -sk "$work/data/db/index-snapshots" | cut -f1) / 1024 ))"
}

restart no_snapshot
start=$(date +%s.%N)
while [ "$(unindexed_codes "$build" scale)" -gt 0 ]; do sleep 5; done
echo "no_snapshot_graph_complete_seconds,$(seconds_since "$start")"
stop_and_report
for run in 1 2 3; do
  restart "snapshot_$run"
  stop_and_report
done
restart snapshot_4
kill -9 "$SERVER_PID"
wait "$SERVER_PID" || true
restart after_kill9
stop_server
