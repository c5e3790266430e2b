#!/bin/bash
# Where a loaded fleet's memory goes: one fleet of 256-d traces (4 robots,
# batches of 200, the restart benchmark's shape: clusters of 10 traces) is
# filled on the exact index, restarted once on the default (tiered) index
# to build the HNSW graph, stopped (the index snapshot is written), then
# started again from the snapshot under heaptrack and, once loaded and
# queried, killed with SIGKILL: what heaptrack saw allocated and not freed
# by then ("leaked") is the heap of the serving process. Prints the RSS
# after the load and the allocation sites that hold the most of that heap,
# so every line of the footprint arithmetic in docs/performance.md has a
# measured figure.
#
#   bench/rss_profile.sh [BUILD_DIR] [TRACES] [OUT_DIR]
#   (default: build 200000 $(mktemp -d); needs Debian's heaptrack)
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
traces=${2:-200000}
out=${3:-$(mktemp -d)}
command -v heaptrack >/dev/null || {
  echo "rss_profile.sh needs heaptrack (apt-get install heaptrack)" >&2
  exit 2
}
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; wait; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
# The graph is built once, then saved by the clean stop.
fill_scale_fleet_once "$build" "$work" "$traces"

# Loaded from the snapshot under heaptrack: the port opens after the load.
SERVER_WRAPPER="heaptrack -o $out/server" SERVER_START_SECONDS=1200 \
  start_server "$build" "$work/data" "$work/profiled.log" \
  --config "$work/restart.textproto"
grep -o 'fleet "scale" loaded.*' "$work/profiled.log"
"$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet scale \
  --dimension 256 --robots 0 --seconds 3 --query-rate 20 >/dev/null 2>&1
rss_mib=$(server_rss_mib "$SERVER_PID")
echo "rss_mib_after_load,$rss_mib"
awk -v r="$rss_mib" -v n="$FILLED" 'BEGIN {
  printf "rss_over_payload,%.2f\nrss_bytes_per_trace,%.0f\n",
    r * 1048576 / (n * 1024), r * 1048576 / n }'
kill -KILL "$(pgrep -P "$SERVER_PID" -f fleetmem-server)"
wait "$SERVER_PID" || true
profile=$(ls "$out"/server*.zst "$out"/server*.gz 2>/dev/null | head -1 || true)
heaptrack_print --print-peaks 0 --print-allocators 0 --print-temporary 0 \
  --print-leaks 1 --peak-limit 40 --sub-peak-limit 0 "$profile" \
  >"$out/held.txt"
grep -E '^(total memory leaked|peak heap)' "$out/held.txt" || true
echo "heaptrack profile: $profile; heap held by site: $out/held.txt"
