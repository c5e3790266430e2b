#!/usr/bin/env bash
# The largest REST read against the real server, with its RSS sampled
# (issue 32: a page of a 4,096-d fleet took the server from 2.2 to 9.0 GB).
# Fills fleet "wide" with TRACES traces of DIMENSION (not consolidated, so
# all are listed), then GETs /v1/fleets/wide/traces?pageSize=10000 while
# sampling the server's VmRSS every 20 ms; prints the page's size and
# traces, the RSS before, and the largest rise during the read. With
# READERS > 1, that many read the page at once; with STALLED, that many
# more ask for it and never read (issue 44: 8 at once took +793 MiB, 16
# readers that never read +2,758 MiB; the goal with 8 and 32: <= 512 MiB).
#
#   tools/load/rest_page_rss.sh [BUILD_DIR] [TRACES] [DIMENSION] [READERS] [STALLED]
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
source "$here/server_lib.sh"
build=${1:-build}
traces=${2:-5200}
dimension=${3:-4096}
readers=${4:-1}
stalled=${5:-0}
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
url="http://$SERVER_HTTP_ADDR/v1/fleets/wide/traces?pageSize=10000"
if [ "$stalled" -gt 0 ]; then
  # Readers that send the request and never read (a small receive buffer),
  # until the server cuts them.
  /usr/bin/python3 - "$SERVER_HTTP_ADDR" "$stalled" >"$dir/stalled.txt" <<'PY' &
import socket, sys, time
host, port = sys.argv[1].rsplit(":", 1)
socks = []
for _ in range(int(sys.argv[2])):
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect((host, int(port)))
    s.sendall(f"GET /v1/fleets/wide/traces?pageSize=10000 HTTP/1.1\r\nHost: {sys.argv[1]}\r\n\r\n".encode())
    socks.append(s)
time.sleep(20)
print(f"{len(socks)} stalled readers held 20 s")
PY
  stalled_pid=$!
  sleep 1
fi
readers_pids=()
for i in $(seq 2 "$readers"); do
  curl -sS -o /dev/null -w "reader $i: HTTP %{http_code}, %{size_download} bytes in %{time_total} s\n" "$url" &
  readers_pids+=($!)
done
curl -sS -o "$dir/page.json" -w 'HTTP %{http_code}, %{size_download} bytes in %{time_total} s\n' "$url"
for pid in "${readers_pids[@]}"; do wait "$pid" || true; done
if [ -n "${stalled_pid:-}" ]; then wait "$stalled_pid" || true; cat "$dir/stalled.txt"; fi
sleep 0.2
kill "$sampler" 2>/dev/null || true
wait "$sampler" 2>/dev/null || true
listed=$(/usr/bin/python3 -c 'import json,sys; d=json.load(open(sys.argv[1])); print(len(d.get("traces",[])), "traces in the page;", "next page token" if d.get("nextPageToken") else "no next page")' "$dir/page.json")
peak=$(cat "$dir/peak")
echo "$listed"
echo "$readers reader(s), $stalled stalled: server RSS before the reads $((before / 1024)) MiB; largest rise during them $(((peak - before) / 1024)) MiB"
stop_server
