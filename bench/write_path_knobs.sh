#!/bin/bash
# The write path's knobs, one server build, one configuration at a time
# (docs/performance.md, "The write path"):
#
#   bench/write_path_knobs.sh BUILD OUT_CSV HELD 'NAME=CONFIG TEXT' ...
#   (e.g. build docs/perf/write_path_knobs.csv 50000 'default=' \
#         'insert_threads_1=hnsw { insert_threads: 1 }')
#
# For each configuration, on a fresh data directory (K_max = HELD / 10 +
# 2,100, nothing forgotten; the configuration text appended):
#   fill    HELD traces (4 streams, batches of 200, 256-d, every code its
#           own), acknowledged once applied: traces/s;
#   burst   10 s of one upload stream (batches of 200, durable
#           acknowledgement) with QueryPlace (k = 10) at 20/s beside:
#           acknowledged/s, query p50/p99;
#   drain   then 10 s of QueryPlace at 50/s and no upload while the burst's
#           backlog is applied: query p50/p99, and the traces applied per
#           second over those 10 s (backlog before - backlog after).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 4 ]; then
  echo "usage: $0 BUILD OUT_CSV HELD NAME=CONFIG..." >&2
  exit 2
fi
build=$1
out=$2
held=$3
shift 3
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
load="$build/bin/fleetmem-load"
echo "config,held,fill_traces_per_s,burst_acked_per_s,burst_query_p50_ms,burst_query_p99_ms,drain_query_p50_ms,drain_query_p99_ms,drain_applied_per_s" >"$out"
for spec in "$@"; do
  name=${spec%%=*}
  text=${spec#*=}
  printf 'memory { max_clusters: %d }\nlimits { max_traces_per_fleet: 4200000 }\n%s\n' \
    $((held / 10 + 2100)) "$text" >"$work/config.textproto"
  rm -rf "$work/data"
  start_server "$build" "$work/data" "$work/server.log" \
    --config "$work/config.textproto"
  fill=$("$load" upload --server "$SERVER_ADDR" --fleet w --dimension 256 \
    --robots 4 --batch 200 --seconds 100000 --traces "$held" --ack applied |
    sed -n 's/.*traces in .* s (\([0-9]*\)\/s).*/\1/p')
  "$load" bench --server "$SERVER_ADDR" --fleet w --dimension 256 \
    --robots 1 --batch 200 --seconds 10 --query-rate 20 \
    --first-seq 2000000 --code-pool 100000 --csv "$work/burst.csv" \
    >/dev/null 2>&1
  before=$(backlog_traces "$build" w)
  start=$(date +%s.%N)
  "$load" bench --server "$SERVER_ADDR" --fleet w --dimension 256 \
    --robots 0 --seconds 10 --query-rate 50 --csv "$work/drain.csv" \
    >/dev/null 2>&1 &
  queries=$!
  sleep 10
  after=$(backlog_traces "$build" w)
  seconds=$(awk -v a="$(date +%s.%N)" -v b="$start" 'BEGIN { print a - b }')
  wait "$queries"
  stop_server
  burst=$(sed -n 2p "$work/burst.csv")
  drain=$(sed -n 2p "$work/drain.csv")
  col() { echo "$1" | cut -d, -f"$2"; }
  printf '%s,%s,%s,%s,%s,%s,%s,%s,%.0f\n' "$name" "$held" "$fill" \
    "$(col "$burst" 6)" "$(col "$burst" 13)" "$(col "$burst" 14)" \
    "$(col "$drain" 13)" "$(col "$drain" 14)" \
    "$(awk -v a="$before" -v b="$after" -v s="$seconds" \
      'BEGIN { print (a - b) / s }')" | tee -a "$out"
done
