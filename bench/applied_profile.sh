#!/bin/bash
# Where the server's CPU goes while it applies uploads it has acknowledged
# (issue 49: the applied rate): one robot uploads N 256-d traces (every
# code its own, batches of 200; K_max large enough that every trace is
# kept), then `perf record -e cpu-clock` samples the server alone for
# SECONDS while it consolidates and indexes them; prints the fleet's stats
# after the sample and the server's samples by symbol.
#
#   bench/applied_profile.sh [BUILD_DIR] [N] [SECONDS]
#   (default: build 100000 15)
# Environment: SERVER_BUILD (the server of another build, e.g. the one
# before a change; the load generator stays BUILD_DIR's), HNSW_CODES (int8
# or float: hnsw { codes }), TOP (25 symbols).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
n=${2:-100000}
seconds=${3:-15}
command -v perf >/dev/null || { echo "perf not found (apt-get install linux-perf)" >&2; exit 2; }
work=$(mktemp -d "${TMPDIR:-/tmp}/applied-profile.XXXXXX")
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
printf 'memory { max_clusters: %d }\nlimits { max_traces_per_fleet: %d }\n' \
  $((n / 10 + 100)) $((n * 2)) >"$work/server.textproto"
if [ -n "${HNSW_CODES:-}" ]; then
  printf 'hnsw { codes: "%s" }\n' "$HNSW_CODES" >>"$work/server.textproto"
fi
start_server "${SERVER_BUILD:-$build}" "$work/data" "$work/server.log" \
  --config "$work/server.textproto"
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet applied \
  --dimension 256 --robots 1 --batch 200 --traces "$n" --seconds 100000 |
  tail -1
perf record -q -e cpu-clock -F 499 -g -p "$SERVER_PID" -o "$work/perf.data" \
  -- sleep "$seconds" 2>/dev/null
"$build/bin/fleetmem" --server "$SERVER_ADDR" stats --fleet applied |
  grep -E '^(traces|write backlog|log applied)'
stop_server
echo "# by symbol (share of the server's samples)"
perf report -i "$work/perf.data" --no-children --sort symbol --stdio \
  -g none 2>/dev/null | grep -v '^#' | grep '%' | sed 's/  */ /g' |
  head -"${TOP:-25}"
