#!/bin/bash
# Where a burst's CPU goes in the server, by thread (issue 30's fourth
# round): fills a fleet to SIZE traces (acknowledged once applied), then
# one upload stream for 10 s (batches of 200, 256-d, a code pool of
# 100,000, durable acknowledgement, no backlog bound, queries at 20/s
# beside, as bench/write_path_bench.sh's burst) while `perf record`
# samples the server for 7 s. Prints the burst's rates and each thread
# name's share of the samples in cores (gRPC's `nexting_thread`, the
# calls' `fleetmem-server` workers, `fleetmem-apply`, `fleetmem-graph`,
# RocksDB's `rocksdb:low` compactions and `rocksdb:high` flushes).
#
#   bench/write_path_profile.sh BUILD [SIZE]   (SIZE 5000 by default)
# The load generator is LOAD_BUILD's (default BUILD): an older server build
# may have none. BATCH (200) sets the traces per call; the client sends a
# call in messages of 500, so BATCH=10000 is a stream of 20 messages, as a
# robot draining its queue sends it.
# Needs perf (Debian's linux-perf) and perf_event_paranoid <= 1 or root.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:?usage: $0 BUILD [SIZE]}
size=${2:-5000}
load="${LOAD_BUILD:-$build}/bin/fleetmem-load"
command -v perf >/dev/null || { echo "perf not found (apt-get install linux-perf)" >&2; exit 2; }
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
cat >"$work/config.textproto" <<CONFIG
memory { max_clusters: $((size / 10 + 2100)) }
limits { max_traces_per_fleet: $((size * 2 + 4000000)) }
write_path { max_backlog_traces: 0 }
CONFIG
start_server "$build" "$work/data" "$work/server.log" \
  --config "$work/config.textproto"
"$load" upload --server "$SERVER_ADDR" --fleet w \
  --dimension 256 --robots 4 --batch 200 --seconds 100000 --traces "$size" \
  --ack applied >/dev/null
"$load" bench --server "$SERVER_ADDR" --fleet w \
  --dimension 256 --robots 1 --batch "${BATCH:-200}" --seconds 10 --query-rate 20 \
  --first-seq 2000000 --code-pool 100000 --csv "$work/burst.csv" \
  >/dev/null 2>&1 &
bench=$!
sleep 1
perf record -F 999 -p "$SERVER_PID" -o "$work/perf.data" -- sleep 7 \
  >/dev/null 2>&1
wait "$bench"
stop_server
row=$(sed -n 2p "$work/burst.csv")
peer=$(sed -n 3p "$work/burst.csv")
echo "burst: $(cut -d, -f6 <<<"$row") traces/s acknowledged; the" \
  "load generator's peer $(cut -d, -f6 <<<"$peer")/s right after it"
echo "server CPU by thread over 7 s of the burst (cores):"
perf report -i "$work/perf.data" --no-children --sort comm -g none -n \
  2>/dev/null | awk '/^ *[0-9.]+%/ { printf "  %-16s %.2f\n", $3, $2 / (999 * 7) }'
