#!/bin/bash
# ctest fleetmem_load_bench_test: `fleetmem-load bench` against the real
# server and its in-process peer prints both and the ratio, and both rows of
# its CSV carry uploads and timed calls.
set -euo pipefail
build=$1
here=$(cd "$(dirname "$0")" && pwd)
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/server_lib.sh"
start_server "$build" "$work/data" "$work/server.log"
"$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --robots 2 \
  --batch 100 --dimension 64 --seconds 1.5 --query-rate 20 --sample-rate 5 \
  --stats-rate 5 --csv "$work/bench.csv" | tee "$work/out.txt"
grep -q '^fleetmem ' "$work/out.txt"
grep -q '^peer ' "$work/out.txt"
grep -q 'fleetmem/peer upload throughput: [0-9.]*' "$work/out.txt"
# target,streams,...,uploads_per_s(6),...,query_calls(12),...,ratio(21)
awk -F, 'NR > 1 { rows++; if ($6 <= 0 || $12 <= 0) bad = 1 }
         END { exit !(rows == 2 && !bad) }' "$work/bench.csv" ||
  { echo "bad CSV:"; cat "$work/bench.csv"; exit 1; }
stop_server
echo "load bench against the server and its peer: OK"
