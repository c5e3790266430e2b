#!/bin/bash
# P1: durable upload throughput of the real server against the bare gRPC
# peer (fleetmem-load bench), 256-d traces in batches of 200, with one and
# with eight streams, 10 s per target, each from an empty data directory,
# default server settings (RocksDB with sync on: every acknowledged batch is
# fsynced). Queries at 20/s run beside.
# P2 over gRPC: a fleet of 5,000 traces, then 20 s of QueryPlace (k = 10) at
# 200/s and nothing else, against the server and the peer (QUERY_CSV).
# Last, what the fsyncs cost: one upload stream for 8 s with RocksDB's sync
# on and off (printed).
#
#   bench/load_bench.sh [BUILD_DIR] [OUT_CSV] [QUERY_CSV]
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
out=${2:-$here/docs/perf/load.csv}
query_out=${3:-$(dirname "$out")/query.csv}
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
first=1
for streams in 1 8; do
  rm -rf "$work/data"
  start_server "$build" "$work/data" "$work/server.log"
  "$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet p1 \
    --dimension 256 --robots "$streams" --batch 200 --seconds 10 \
    --query-rate 20 --csv "$work/run.csv"
  stop_server
  if [ $first = 1 ]; then head -1 "$work/run.csv" >"$out"; first=0; fi
  tail -n +2 "$work/run.csv" >>"$out"
done
cat "$out"
rm -rf "$work/data"
start_server "$build" "$work/data" "$work/server.log"
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet p2 \
  --dimension 256 --robots 4 --batch 200 --seconds 1000 --traces 5000 \
  >/dev/null
"$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet p2 \
  --dimension 256 --robots 0 --seconds 20 --query-rate 200 \
  --csv "$query_out" >/dev/null
stop_server
cat "$query_out"
printf 'storage { sync: false }\n' >"$work/nosync.textproto"
for sync in on off; do
  rm -rf "$work/data"
  args=()
  [ $sync = off ] && args=(--config "$work/nosync.textproto")
  start_server "$build" "$work/data" "$work/server.log" "${args[@]}"
  echo "sync $sync: $("$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" \
    --fleet p1 --dimension 256 --robots 1 --batch 200 --seconds 8 | tail -1)"
  stop_server
done
