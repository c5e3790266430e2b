#!/usr/bin/env bash
# Soak: a server under half of its measured peak upload load (plus 20
# queries/s) for SECONDS, sampled every INTERVAL: RSS, open files, upload
# and query latency, and what RSS is made of (the heap's in-use and free
# bytes, RocksDB's memtables, table readers and block cache, from the
# server's /metrics). Ends with a clean SIGTERM. The CSV goes to REPORT.
# SERVER_ARGS: more arguments for the server (e.g. "--config FILE");
# LOAD_ARGS: more for fleetmem-load soak (e.g. "--rate 15000": a fixed rate
# instead of half the measured peak, to compare two servers).
#
#   tools/load/soak.sh [BUILD_DIR] [SECONDS] [INTERVAL] [REPORT]   (make soak)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
source "$here/server_lib.sh"
build=${1:-build}
seconds=${2:-3600}
interval=${3:-60}
report=${4:-soak.csv}
dir=$(mktemp -d "${TMPDIR:-/tmp}/fleetmem-soak-XXXXXX")
trap 'kill -9 ${SERVER_PID:-0} 2>/dev/null || true; rm -rf "$dir"' EXIT
# shellcheck disable=SC2086  # SERVER_ARGS and LOAD_ARGS are lists of words
start_server "$build" "$dir/data" "$dir/server.log" \
  --http-listen 127.0.0.1:0 ${SERVER_ARGS:-}
echo "soak: server $SERVER_ADDR, HTTP $SERVER_HTTP_ADDR (pid $SERVER_PID), $seconds s, samples every $interval s"
"$build/bin/fleetmem-load" soak --server "$SERVER_ADDR" --pid "$SERVER_PID" \
  --seconds "$seconds" --interval "$interval" --report "$report" \
  --metrics "$SERVER_HTTP_ADDR" ${LOAD_ARGS:-}
stop_server
echo "soak: clean shutdown; samples in $report"
