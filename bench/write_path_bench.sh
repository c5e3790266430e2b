#!/bin/bash
# The write path (issue 30): acknowledged and applied upload rates of two
# server builds at several sizes held, with the bare gRPC peer in the same
# run, and query latency while the applier works.
#
#   bench/write_path_bench.sh BEFORE_BUILD AFTER_BUILD OUT_CSV SIZES...
#   (e.g. build-before build docs/perf/write_path.csv 5000 100000)
#
# For each size, each build in turn (before, then after) on a fresh data
# directory, with memory bounds that forget nothing (K_max = size / 10 +
# 100, as bench/server_scale.sh) and no backlog bound (what is measured is
# how fast an acknowledgement can be, not where the bound stops a burst):
#   fill    the fleet to SIZE traces (4 streams, batches of 200, 256-d,
#           every code its own; acknowledged once applied);
#   applied 20,000 more traces on 4 streams, acknowledged at the durable
#           append, and the time until GetStats says all are applied
#           (backlog 0); the build before acknowledges only once applied:
#           its rate is the same number;
#   burst   10 s of one upload stream (batches of 200, a code pool of 100,000:
#           the client's cost stays small), durable acknowledgement, with
#           QueryPlace (k = 10) at 20/s beside it (fleetmem-load bench; it
#           then runs the same 10 s against its in-process bare peer, while
#           the server applies the burst: the peer's query latency is what
#           gRPC alone gives on this machine under that load);
#   drain   right after the burst, 10 s of QueryPlace (k = 10) at 50/s and
#           no upload, while the applier works through the burst's backlog
#           (then 10 s of the same against the load generator's own peer),
#           and the traces applied per second over those 20 s (GetStats'
#           backlog before and after; the server is then stopped without
#           waiting for the rest: a burst of a million traces takes minutes
#           to apply);
#   peer    then, with the server idle, the same stream for 10 s against the
#           bare gRPC peer of the same proto (fleetmem-load peer).
# The load generator is AFTER's (the build before ignores the `ack` field).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 4 ]; then
  echo "usage: $0 BEFORE_BUILD AFTER_BUILD OUT_CSV SIZES..." >&2
  exit 2
fi
before=$1
after=$2
out=$3
shift 3
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
load="$after/bin/fleetmem-load"

# wait_applied FLEET: seconds until the fleet's backlog is empty.
wait_applied() {
  local start
  start=$(date +%s.%N)
  while [ "$(backlog_traces "$after" "$1")" != 0 ]; do sleep 0.05; done
  awk -v a="$(date +%s.%N)" -v b="$start" 'BEGIN { printf "%.3f", a - b }'
}
calc() { awk "BEGIN { printf \"%.6f\", $1 }"; }

echo "size,build,applied_traces_per_s,burst_acked_per_s,peer_per_s,ratio_to_peer,burst_query_p50_ms,burst_query_p99_ms,drain_applied_per_s,burst_traces,drain_query_p50_ms,drain_query_p99_ms,peer_query_p50_ms,peer_query_p99_ms" >"$out"
for size in "$@"; do
  cat >"$work/config.textproto" <<CONFIG
memory { max_clusters: $((size / 10 + 2100)) }
limits { max_traces_per_fleet: $((size * 2 + 4000000)) }
write_path { max_backlog_traces: 0 }
CONFIG
  for which in before after; do
    build=$before
    [ $which = after ] && build=$after
    rm -rf "$work/data"
    start_server "$build" "$work/data" "$work/server.log" \
      --config "$work/config.textproto"
    "$load" upload --server "$SERVER_ADDR" --fleet w --dimension 256 \
      --robots 4 --batch 200 --seconds 100000 --traces "$size" --ack applied \
      >/dev/null
    # Sustained applied rate at SIZE: 20,000 traces, durable ack, then
    # until applied.
    start=$(date +%s.%N)
    "$load" upload --server "$SERVER_ADDR" --fleet w --dimension 256 \
      --robots 4 --batch 200 --seconds 100000 --traces 20000 \
      --first-seq 1000000 >/dev/null
    wait_applied w >/dev/null
    applied=$(calc "20000 / ($(date +%s.%N) - $start)")
    # Burst: one stream for 10 s, queries beside, the peer after it.
    "$load" bench --server "$SERVER_ADDR" --fleet w --dimension 256 \
      --robots 1 --batch 200 --seconds 10 --query-rate 20 \
      --first-seq 2000000 --code-pool 100000 --csv "$work/burst.csv" \
      >/dev/null 2>&1
    backlog_start=$(backlog_traces "$after" w)
    drain_start=$(date +%s.%N)
    "$load" bench --server "$SERVER_ADDR" --fleet w --dimension 256 \
      --robots 0 --seconds 10 --query-rate 50 --csv "$work/drain.csv" \
      >/dev/null 2>&1
    drain=$(calc "($backlog_start - $(backlog_traces "$after" w)) / ($(date +%s.%N) - $drain_start)")
    stop_server
    "$load" peer --listen 127.0.0.1:0 >"$work/peer.txt" &
    peer_pid=$!
    until grep -q "listening on" "$work/peer.txt" 2>/dev/null; do sleep 0.05; done
    peer_addr=$(sed -n 's/.*listening on //p' "$work/peer.txt")
    peer_rate=$("$load" upload --server "$peer_addr" --fleet w --dimension 256 \
      --robots 1 --batch 200 --seconds 10 --code-pool 100000 |
      sed -n 's/.*traces in .* s (\([0-9]*\)\/s).*/\1/p')
    kill "$peer_pid"
    wait "$peer_pid" 2>/dev/null || true
    row=$(sed -n 2p "$work/burst.csv")
    peer_row=$(sed -n 3p "$work/burst.csv")
    drain_row=$(sed -n 2p "$work/drain.csv")
    col() { echo "$1" | cut -d, -f"$2"; }
    acked=$(col "$row" 6)
    printf '%s,%s,%.0f,%s,%s,%.3f,%s,%s,%.0f,%.0f,%s,%s,%s,%s\n' "$size" "$which" \
      "$applied" "$acked" "$peer_rate" \
      "$(calc "$acked / $peer_rate")" "$(col "$row" 13)" \
      "$(col "$row" 14)" "$drain" "$(calc "$acked * 10")" \
      "$(col "$drain_row" 13)" "$(col "$drain_row" 14)" \
      "$(col "$peer_row" 13)" "$(col "$peer_row" 14)" |
      tee -a "$out"
  done
done
