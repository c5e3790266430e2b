#!/bin/bash
# Where the server's CPU goes while it acknowledges a burst of concurrent
# robots (issue 49): ROBOTS (8) upload streams for 12 s (256-d, batches of
# 200, a pool of 1,000 codes per robot, durable acknowledgement) into a
# fresh server, as bench/ack_streams_bench.sh's; `perf record -e cpu-clock`
# samples the server for 8 s of it. Prints the load's rate and the top
# symbols and libraries by share of the server's samples.
#
#   bench/ack_profile.sh [BUILD_DIR]
# Environment: SERVER_BUILD, a build whose fleetmem-server is profiled
# (default BUILD_DIR; the load generator is BUILD_DIR's), e.g. the build
# before a change; ROBOTS (8); TOP (25) lines of each table.
# Needs perf (Debian's linux-perf) and perf_event_paranoid <= 1 or root.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
robots=${ROBOTS:-8}
command -v perf >/dev/null || { echo "perf not found (apt-get install linux-perf)" >&2; exit 2; }
work=$(mktemp -d "${TMPDIR:-/tmp}/ack-profile.XXXXXX")
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
printf 'limits { max_streams_per_client: 1024 max_traces_per_fleet: 100000000 }\n' \
  >"$work/server.textproto"
start_server "${SERVER_BUILD:-$build}" "$work/data" "$work/server.log" \
  --config "$work/server.textproto"
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet ack \
  --dimension 256 --robots "$robots" --batch 200 --seconds 12 \
  --code-pool 1000 >"$work/load.txt" &
load=$!
sleep 2
perf record -q -e cpu-clock -F 499 -g -p "$SERVER_PID" -o "$work/perf.data" \
  -- sleep 8 2>/dev/null
wait "$load"
cat "$work/load.txt"
stop_server
for key in symbol dso; do
  echo "# by $key (share of the server's samples)"
  perf report -i "$work/perf.data" --no-children --sort "$key" --stdio \
    -g none 2>/dev/null | grep -v '^#' | grep '%' | sed 's/  */ /g' |
    head -${TOP:-25}
done
