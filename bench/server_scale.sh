#!/bin/bash
# The real server as one fleet fills (issue: upload flat as a fleet fills,
# P2 over gRPC, GetStats/SampleReplay at size, restart time, P7 footprint).
#
#   bench/server_scale.sh [BUILD_DIR] [OUT_CSV] [SIZES...]
#   (default: build docs/perf/server_scale.csv 5000 20000 100000 200000)
#
# One fleet of 256-d traces (4 robots, batches of 200, every code its own;
# fleetmem-load upload) is filled to each size in turn; at each size it
# records the fill's upload rate since the previous size, then runs
# `fleetmem-load bench --robots 0` for 5 s (QueryPlace k=10 at 50/s,
# SampleReplay of 1,000 at 5/s, GetStats at 10/s, against the server and the
# bare gRPC peer), the server's RSS and the data directory's size. After the
# largest size it stops the server (SIGTERM) and times a restart until the
# port answers, then 5 s of queries while the place graph refills in the
# background, and the time until it is complete (GetStats unindexed_codes
# = 0) with the RSS then. The memory is bounded so that nothing is forgotten (K_max =
# the largest size / 10 clusters). Raw payload = traces x 256 x 4 bytes.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
out=${2:-$here/docs/perf/server_scale.csv}
shift 2 2>/dev/null || shift $#
sizes=("$@")
[ ${#sizes[@]} -gt 0 ] || sizes=(5000 20000 100000 200000)
largest=${sizes[-1]}
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
config="$work/server.textproto"
cat >"$config" <<CONFIG
memory { max_clusters: $((largest / 10 + 100)) }
limits { max_traces_per_fleet: $((largest * 2)) }
CONFIG
start_server "$build" "$work/data" "$work/server.log" --config "$config"
load="$build/bin/fleetmem-load"
echo "size,fill_traces_per_s,query_p50_ms,query_p99_ms,peer_query_p50_ms,sample_p50_ms,sample_p99_ms,stats_p50_ms,stats_p99_ms,rss_mib,disk_mib,payload_mib" >"$out"
filled=0
for size in "${sizes[@]}"; do
  start=$(date +%s.%N)
  "$load" upload --server "$SERVER_ADDR" --fleet scale --dimension 256 \
    --robots 4 --batch 200 --seconds 100000 --traces $((size - filled)) \
    --first-seq $((filled / 4 + 1)) >"$work/upload.txt"
  end=$(date +%s.%N)
  rate=$(sed -n 's/.*traces in .* s (\([0-9]*\)\/s).*/\1/p' "$work/upload.txt")
  filled=$size
  "$load" bench --server "$SERVER_ADDR" --fleet scale --dimension 256 \
    --robots 0 --seconds 5 --query-rate 50 --sample-rate 5 --stats-rate 10 \
    --csv "$work/calls.csv" >/dev/null 2>&1
  server_row=$(sed -n 2p "$work/calls.csv")
  peer_row=$(sed -n 3p "$work/calls.csv")
  col() { echo "$1" | cut -d, -f"$2"; }
  rss=$(( $(ps -o rss= -p "$SERVER_PID") / 1024 ))
  disk=$(( $(du -sb "$work/data" | cut -f1) / 1048576 ))
  payload=$(( size * 256 * 4 / 1048576 ))
  echo "$size,$rate,$(col "$server_row" 13),$(col "$server_row" 14),$(col "$peer_row" 13),$(col "$server_row" 16),$(col "$server_row" 17),$(col "$server_row" 19),$(col "$server_row" 20),$rss,$disk,$payload" | tee -a "$out"
done
stop_server
start=$(date +%s.%N)
SERVER_START_SECONDS=3600 start_server "$build" "$work/data" \
  "$work/restart.log" --config "$config"
end=$(date +%s.%N)
restart=$(awk "BEGIN { printf \"%.2f\", $end - $start }")
echo "restart_seconds_at_$largest,$restart" | tee -a "$out"
# Where the restart went (the engine logs each fleet's load).
grep -o 'fleet "scale" loaded.*' "$work/restart.log" >&2 || true
unindexed() { unindexed_codes "$build" scale; }
echo "restart_unindexed_codes_at_open,$(unindexed)" | tee -a "$out"
"$load" bench --server "$SERVER_ADDR" --fleet scale --dimension 256 \
  --robots 0 --seconds 5 --query-rate 20 --csv "$work/calls.csv" >/dev/null 2>&1
echo "restart_query_p50_ms_while_refilling,$(sed -n 2p "$work/calls.csv" | cut -d, -f13)" | tee -a "$out"
left=$(unindexed)
while [ -n "$left" ] && [ "$left" -gt 0 ]; do
  sleep 5
  left=$(unindexed)
done
end=$(date +%s.%N)
echo "restart_graph_complete_seconds,$(awk "BEGIN { printf \"%.0f\", $end - $start }")" | tee -a "$out"
echo "restart_rss_mib_graph_complete,$(( $(ps -o rss= -p "$SERVER_PID") / 1024 ))" | tee -a "$out"
stop_server
