#!/bin/bash
# Acknowledged upload throughput at 1, 8 and 64 concurrent streams: the real
# server beside its two peers in one run (fleetmem-load bench): the bare
# gRPC peer (parses and discards) and the durable peer (appends each
# message to one file and fdatasyncs it before answering, one message at a
# time, no grouping). 256-d traces in batches of 200 from a pool of 1,000
# codes per robot (the client is not the limit), 10 s per target, the
# server from an empty data directory with its default settings (uploads
# acknowledged at the synced append of its fleet log) but two limits that a
# 10 s burst from one host meets: every stream comes from 127.0.0.1
# (max_streams_per_client 1024) and a fleet fills past 1,000,000 traces
# (max_traces_per_fleet 100,000,000). The peer's file and the server's
# data directory are on the same file system.
#
#   bench/ack_streams_bench.sh [BUILD_DIR] [OUT_CSV] [STREAMS...]
# Environment: SERVER_BUILD, a build whose fleetmem-server is measured
# (default BUILD_DIR; the load generator and the peers are BUILD_DIR's),
# e.g. the build before a change.
#
# OUT_CSV gets fleetmem-load bench's rows for every stream count
# (ratio_to_peer: the bare peer; ratio_to_durable: the durable one).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
out=${2:-$here/docs/perf/ack_streams.csv}
shift 2 || true
streams_list=("$@")
[ ${#streams_list[@]} -gt 0 ] || streams_list=(1 8 64)
work=$(mktemp -d "${TMPDIR:-/tmp}/ack-streams.XXXXXX")
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
printf 'limits { max_streams_per_client: 1024 max_traces_per_fleet: 100000000 }\n' \
  >"$work/server.textproto"
first=1
for streams in "${streams_list[@]}"; do
  rm -rf "$work/data" "$work/durable-peer.log"
  start_server "${SERVER_BUILD:-$build}" "$work/data" "$work/server.log" \
    --config "$work/server.textproto"
  "$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet ack \
    --dimension 256 --robots "$streams" --batch 200 --seconds 10 \
    --code-pool 1000 --durable-peer-dir "$work" --csv "$work/run.csv"
  stop_server
  if [ $first = 1 ]; then head -1 "$work/run.csv" >"$out"; first=0; fi
  tail -n +2 "$work/run.csv" >>"$out"
done
cat "$out"
