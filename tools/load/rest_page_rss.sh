#!/usr/bin/env bash
# The largest REST read against the real server, with its RSS sampled
# (issue 32: a page of a 4,096-d fleet took the server from 2.2 to 9.0 GB).
# Fills fleet "wide" with TRACES traces of DIMENSION (not consolidated, so
# all are listed), then GETs /v1/fleets/wide/traces?pageSize=10000 while
# sampling the server's VmRSS every 20 ms; prints the page's size and
# traces, the RSS before, and the largest rise during the read.
#
#   tools/load/rest_page_rss.sh [BUILD_DIR] [TRACES] [DIMENSION]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
source "$here/server_lib.sh"
build=${1:-build}
traces=${2:-5200}
dimension=${3:-4096}
dir=$(mktemp -d "${TMPDIR:-/tmp}/fleetmem-restrss-XXXXXX")
trap 'kill -9 ${SERVER_PID:-0} ${sampler:-0} 2>/dev/null || true; rm -rf "$dir"' EXIT
printf 'engine { segment_size: 1000000 }\nlimits { max_traces_per_fleet: %d }\n' \
  $((traces * 2)) >"$dir/config.textproto"
start_server "$build" "$dir/data" "$dir/server.log" \
  --http-listen 127.0.0.1:0 --config "$dir/config.textproto"
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet wide \
  --dimension "$dimension" --robots 1 --batch 100 --seconds 600 \
  --traces "$traces" | tail -1
rss_kib() { sed -n 's/^VmRSS:[[:space:]]*\([0-9]*\).*/\1/p' "/proc/$SERVER_PID/status"; }
before=$(rss_kib)
( peak=$before
  while :; do
    now=$(rss_kib)
    [ "$now" -gt "$peak" ] && peak=$now && echo "$peak" >"$dir/peak"
    sleep 0.02
  done ) &
sampler=$!
echo "$before" >"$dir/peak"
curl -sS -o "$dir/page.json" -w 'HTTP %{http_code}, %{size_download} bytes in %{time_total} s\n' \
  "http://$SERVER_HTTP_ADDR/v1/fleets/wide/traces?pageSize=10000"
sleep 0.2
kill "$sampler" 2>/dev/null || true
wait "$sampler" 2>/dev/null || true
listed=$(/usr/bin/python3 -c 'import json,sys; d=json.load(open(sys.argv[1])); print(len(d.get("traces",[])), "traces in the page;", "next page token" if d.get("nextPageToken") else "no next page")' "$dir/page.json")
peak=$(cat "$dir/peak")
echo "$listed"
echo "server RSS before the read $((before / 1024)) MiB; largest rise during it $(((peak - before) / 1024)) MiB"
stop_server
