#!/usr/bin/env bash
# Soak: a server under half of its measured peak upload load (plus 20
# queries/s) for SECONDS, sampled every INTERVAL: RSS, open files, upload
# and query latency. Ends with a clean SIGTERM. The CSV goes to REPORT.
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
start_server "$build" "$dir/data" "$dir/server.log"
echo "soak: server $SERVER_ADDR (pid $SERVER_PID), $seconds s, samples every $interval s"
"$build/bin/fleetmem-load" soak --server "$SERVER_ADDR" --pid "$SERVER_PID" \
  --seconds "$seconds" --interval "$interval" --report "$report"
stop_server
echo "soak: clean shutdown; samples in $report"
