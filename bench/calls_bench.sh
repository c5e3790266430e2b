#!/bin/bash
# SampleReplay's latency on two server builds (issue 45, fifth round:
# embedded mode's Consolidate and SampleReplay became log entries, each a
# synced append applied by the write path's appliers), alternated in one
# run, with the bare gRPC peer of the same proto in each phase.
#
#   bench/calls_bench.sh BEFORE_BUILD AFTER_BUILD OUT_CSV ROUNDS
#   (e.g. build-before build docs/perf/calls.csv 2)
#
# Each round runs before, then after, each on a fresh data directory: the
# fleet filled to 5,000 traces (4 streams, 256-d, acknowledged once
# applied), then
#   idle    10 s of SampleReplay (1,000 traces a call) at 10/s, nothing else;
#   loaded  the same beside one upload stream (batches of 200, durable
#           acknowledgement) that the appliers work behind.
# fleetmem-load bench runs each phase against the server, then against its
# in-process peer. The load generator is AFTER's.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 4 ]; then
  echo "usage: $0 BEFORE_BUILD AFTER_BUILD OUT_CSV ROUNDS" >&2
  exit 2
fi
before=$1 after=$2 out=$3 rounds=$4
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
load="$after/bin/fleetmem-load"
col() { echo "$1" | cut -d, -f"$2"; }

echo "round,build,phase,sample_calls,sample_p50_ms,sample_p99_ms,peer_sample_p50_ms,peer_sample_p99_ms,uploads_per_s" >"$out"
for round in $(seq 1 "$rounds"); do
  for which in before after; do
    build=$before
    [ $which = after ] && build=$after
    rm -rf "$work/data"
    start_server "$build" "$work/data" "$work/server.log"
    "$load" upload --server "$SERVER_ADDR" --fleet c --dimension 256 \
      --robots 4 --batch 200 --seconds 100000 --traces 5000 --ack applied \
      >/dev/null
    for phase in idle loaded; do
      robots=0
      [ $phase = loaded ] && robots=1
      "$load" bench --server "$SERVER_ADDR" --fleet c --dimension 256 \
        --robots $robots --batch 200 --seconds 10 --sample-rate 10 \
        --first-seq $((1000000 * round)) --code-pool 100000 \
        --csv "$work/$phase.csv" >/dev/null 2>&1
      row=$(sed -n 2p "$work/$phase.csv")
      peer=$(sed -n 3p "$work/$phase.csv")
      printf '%s,%s,%s,%s,%s,%s,%s,%s,%s\n' "$round" "$which" "$phase" \
        "$(col "$row" 15)" "$(col "$row" 16)" "$(col "$row" 17)" \
        "$(col "$peer" 16)" "$(col "$peer" 17)" "$(col "$row" 6)" | tee -a "$out"
    done
    stop_server
  done
done
