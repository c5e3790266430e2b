#!/bin/bash
# Restart at 1,000,000 traces, with and without the index snapshot a clean
# shutdown writes. One fleet of 256-d traces (4 robots, batches of 200) is
# filled on the exact index (`index: "exact"`; it prints the fill rate). The
# server is then started on the default (tiered) index, which rebuilds the
# HNSW graph in the background (the path after a crash: timed until GetStats
# shows no unindexed code), and stopped with SIGTERM, which saves the
# snapshot. Three restarts follow, each timed until the port answers, with
# the codes outside the graph at that moment, the median query over the
# next 5 s, the engine's load lines and the RSS; the snapshot is kept and
# not written again while nothing changed. Last, the path after a crash
# with index snapshots while serving: a server whose last snapshot is
# behind by TAIL traces (uploaded after it, 20,000 by default) is killed
# with kill -9 and restarted, timed until the port answers and until the
# graph holds every code again. The rebuild without any snapshot, first
# above, is its peer. Then one periodic snapshot of the full fleet is timed
# (the fleet's uploads wait that long).
#
#   bench/restart_bench.sh [BUILD_DIR] [TRACES] [TAIL]
#   (default: build 1000000 20000)
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
traces=${2:-1000000}
tail_traces=${3:-20000}
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; wait; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
fill_scale_fleet "$build" "$work" "$traces"

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
  grep -o 'fleet "scale": \(loaded from\|rebuilding\|forgetting\|index snapshot reconciled\).*' "$work/restart.log" || true
  grep -o 'fleet "scale" loaded.*' "$work/restart.log"
  echo "$1_rss_mib_after_load,$(( $(ps -o rss= -p "$SERVER_PID") / 1024 ))"
}

# stop_and_report: SIGTERM (the snapshot is written) and its size and time.
stop_and_report() {
  stop_server
  grep -o 'fleet "scale": index snapshot of.*' "$work/restart.log" ||
    echo "(no snapshot written: the one on disk is current)"
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

# After a crash, with a snapshot behind by the tail: the tail is uploaded
# after the snapshot the last stop wrote (a periodic snapshot is the same
# file), then kill -9.
restart before_tail
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet scale \
  --dimension 256 --robots 4 --batch 200 --seconds 100000 \
  --traces "$tail_traces" --first-seq $((traces + 1)) | tail -1
kill -9 "$SERVER_PID"
wait "$SERVER_PID" || true
# Timed until the port answers and until the graph holds every code.
start=$(date +%s.%N)
start_server "$build" "$work/data" "$work/restart.log" \
  --config "$work/restart.textproto"
echo "after_kill9_with_snapshot_restart_seconds,$(seconds_since "$start")"
echo "after_kill9_with_snapshot_unindexed_codes_at_open,$(unindexed_codes "$build" scale)"
while [ "$(unindexed_codes "$build" scale)" -gt 0 ]; do sleep 0.2; done
echo "after_kill9_with_snapshot_graph_complete_seconds,$(seconds_since "$start")"
grep -o 'fleet "scale": \(loaded from\|rebuilding\|forgetting\|index snapshot reconciled\).*' "$work/restart.log" || true
grep -o 'fleet "scale" loaded.*' "$work/restart.log"
echo "after_kill9_with_snapshot_rss_mib_after_load,$(( $(ps -o rss= -p "$SERVER_PID") / 1024 ))"

# One periodic snapshot of the whole fleet, timed by the server (uploads of
# the fleet wait that long; queries do not).
stop_server
printf 'index_snapshot_interval_seconds: 5\n%s\n' "$LIMITS" \
  >"$work/periodic.textproto"
start_server "$build" "$work/data" "$work/periodic.log" \
  --config "$work/periodic.textproto"
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet scale \
  --dimension 256 --robots 1 --batch 200 --seconds 100000 --traces 200 \
  --first-seq $((2 * traces + 1)) | tail -1
for _ in $(seq 1 120); do
  grep -q 'codes saved in' "$work/periodic.log" && break
  sleep 1
done
grep -o 'fleet "scale": index snapshot of.*' "$work/periodic.log"
echo "snapshot_mib,$(( $(du -sk "$work/data/db/index-snapshots" | cut -f1) / 1024 ))"
stop_server
