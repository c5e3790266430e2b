#!/bin/bash
# Queries and SampleReplay of two server builds on the same fleet, with the
# graph's floats in the page cache and out of it, alternating: a fleet of
# TRACES 256-d traces (the restart benchmark's shape) is filled and its
# int8 graph built and saved with B's build (floats kept in a file, the
# default); then ROUNDS rounds each start A's server and B's on a copy of
# that data dir and, once the port answers, run the load generator's
# queries (20/s, k = 10, each rescoring 40 candidates' floats) and samples
# (SampleReplay of 1,000, 5/s) for SECONDS twice: first as the load left
# the page cache ("warm": the floats were just written into their file),
# then after the page cache is written back and dropped ("cold": every
# row read comes from the disk, as on a host that reclaims page cache
# nobody touched for a while). Prints p50 and p99 of each call in ms.
# Then, the page cache dropped again and the memory made full (K_max
# lowered to the clusters held), CONSOLIDATE_TRACES more traces are
# uploaded by one robot in segments of 200, so that every consolidation
# forgets by merging, and the mean consolidation time (the server's
# histogram), the seconds until all are applied (store writes
# included) and the server's bytes read and written meanwhile are printed
# as a `#` row. Last, the page cache dropped once
# more, REWARD_CALLS (5) UpdateRewards of 1,000 random keys each (their
# mean time, the server's histogram, as a `#` row). Needs root
# (/proc/sys/vm/drop_caches).
#
#   bench/cold_rows_ab.sh A_BUILD_DIR B_BUILD_DIR [TRACES] [ROUNDS] [SECONDS]
#   (default: 200000 traces, 2 rounds, 15 s)
# KEEP=DIR keeps the filled fleet for the next run (fill_scale_fleet_once).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 2 ]; then
  echo "usage: $0 A_BUILD_DIR B_BUILD_DIR [TRACES] [ROUNDS] [SECONDS]" >&2
  exit 2
fi
a=$1
b=$2
traces=${3:-200000}
rounds=${4:-2}
seconds=${5:-15}
for tool in "$a/bin/fleetmem-server" "$b/bin/fleetmem-server" \
  "$b/bin/fleetmem" "$b/bin/fleetmem-load"; do
  if [ ! -x "$tool" ]; then
    echo "$tool: no such executable (build it first)" >&2
    exit 2
  fi
done
if [ ! -w /proc/sys/vm/drop_caches ]; then
  echo "$0 drops the page cache: run it as root" >&2
  exit 2
fi
consolidate_traces=${CONSOLIDATE_TRACES:-20000}
reward_calls=${REWARD_CALLS:-5}
source "$here/tools/load/server_lib.sh"
bench_work cold_rows data-run
fill_scale_fleet_once "$b" "$WORK" "$traces"

# calls LABEL: the load generator's queries and samples for SECONDS, one
# CSV row (build, round, cache, p50s and p99s).
calls() {
  "$b/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet scale \
    --dimension 256 --robots 0 --seconds "$seconds" --query-rate 20 \
    --sample-rate 5 --csv "$WORK/calls.csv" >/dev/null 2>&1
  local row
  row=$(sed -n 2p "$WORK/calls.csv")
  echo "$1,$(cut -d, -f12-14 <<<"$row"),$(cut -d, -f15-17 <<<"$row")"
}

# stat NAME: the fleet's GetStats field NAME.
stat() {
  "$b/bin/fleetmem" --server "$SERVER_ADDR" --json stats --fleet scale |
    /usr/bin/python3 -c \
      'import json, sys; print(int(json.load(sys.stdin).get(sys.argv[1], 0)))' "$1"
}
# io_bytes: the server's bytes read from and written to storage so far
# (/proc/PID/io read_bytes write_bytes: every thread, RocksDB's flushes
# and compactions included).
io_bytes() {
  awk '/^read_bytes/ { r = $2 } /^write_bytes/ { w = $2 } END { print r, w }' \
    "/proc/$SERVER_PID/io"
}
# consolidations LABEL: CONSOLIDATE_TRACES uploaded into the full memory
# with a cold page cache; a `#` row with the mean consolidation time.
consolidations() {
  "$b/bin/fleetmem" --server "$SERVER_ADDR" update-fleet --fleet scale \
    --max-clusters "$(stat clusters)" >/dev/null
  local forgotten0 sum0 count0 sum1 count1
  forgotten0=$(stat clustersForgotten)
  sync
  echo 3 >/proc/sys/vm/drop_caches
  read -r sum0 count0 < <(consolidation_metric)
  local t0 read0 written0 read1 written1
  t0=$(date +%s.%N)
  read -r read0 written0 < <(io_bytes)
  "$b/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet scale \
    --dimension 256 --robots 1 --batch 200 --seconds 100000 \
    --first-seq 100000000 \
    --traces "$consolidate_traces" >/dev/null
  while [ "$(backlog_traces "$b" scale)" -gt 0 ]; do sleep 0.2; done
  local t1
  t1=$(date +%s.%N)
  read -r read1 written1 < <(io_bytes)
  read -r sum1 count1 < <(consolidation_metric)
  awk -v l="$1" -v s0="$sum0" -v s1="$sum1" -v a="$count0" -v b="$count1" \
    -v f="$(($(stat clustersForgotten) - forgotten0))" -v t="$t1 - $t0" \
    -v r="$((read1 - read0))" -v w="$((written1 - written0))" \
    'BEGIN { split(t, s, " - ");
             printf "# %s: %d consolidations, %d clusters forgotten, mean %.2f ms; all applied after %.1f s; %.1f MiB read, %.1f MiB written\n",
             l, b - a, f, (b > a ? 1000 * (s1 - s0) / (b - a) : 0), s[1] - s[2],
             r / 1048576, w / 1048576 }'
}

# rewards_metric: UpdateRewards' latency histogram's sum and count.
rewards_metric() {
  curl -s "http://$SERVER_HTTP_ADDR/metrics" |
    awk '/^fleetmem_rpc_duration_seconds_(sum|count)\{.*method="UpdateRewards"/ { v[$1 ~ /_sum/] += $2 }
         END { printf "%s %s\n", v[1], v[0] }'
}
# rewards LABEL ROUND: REWARD_CALLS UpdateRewards of 1,000 random keys of
# the fill's robots each (the same keys for both builds of a round), the
# page cache dropped first; a `#` row with the traces updated and the mean
# call time.
rewards() {
  local sum0 count0 sum1 count1 call updated=0 n read0 written0 read1 written1
  sync
  echo 3 >/proc/sys/vm/drop_caches
  read -r sum0 count0 < <(rewards_metric)
  read -r read0 written0 < <(io_bytes)
  for call in $(seq 1 "$reward_calls"); do
    /usr/bin/python3 -c '
import random, sys
rng = random.Random(int(sys.argv[1]))
for _ in range(1000):
    print("{\"robotId\":\"load-%d\",\"seq\":\"%d\",\"rewardExternal\":%.3f,\"rewardInternal\":0.1}"
          % (rng.randrange(4), rng.randint(1, int(sys.argv[2])), rng.random()))
' "$((1000 * $2 + call))" "$((traces / 4))" >"$WORK/rewards.jsonl"
    n=$("$b/bin/fleetmem" --server "$SERVER_ADDR" --json update-rewards \
      --fleet scale --file "$WORK/rewards.jsonl" |
      /usr/bin/python3 -c 'import json, sys; print(int(json.load(sys.stdin).get("updated", 0)))')
    updated=$((updated + n))
  done
  read -r sum1 count1 < <(rewards_metric)
  read -r read1 written1 < <(io_bytes)
  awk -v l="$1" -v s0="$sum0" -v s1="$sum1" -v a="$count0" -v b="$count1" \
    -v u="$updated" -v r="$((read1 - read0))" -v w="$((written1 - written0))" \
    'BEGIN { printf "# %s: %d UpdateRewards of 1,000 keys, %d traces updated, mean %.2f ms; %.1f MiB read, %.1f MiB written\n",
             l, b - a, u, (b > a ? 1000 * (s1 - s0) / (b - a) : 0),
             r / 1048576, w / 1048576 }'
}

echo "build,round,cache,query_calls,query_p50_ms,query_p99_ms,sample_calls,sample_p50_ms,sample_p99_ms"
for round in $(seq 1 "$rounds"); do
  for build in "$a" "$b"; do
    # One copy at a time (a copy of a 10,000,000-trace fill is 27 GB).
    serve_fill_copy "$build" "$WORK" data-run "$WORK/serve.log"
    calls "$build,$round,warm"
    sync
    echo 3 >/proc/sys/vm/drop_caches
    calls "$build,$round,cold"
    consolidations "$build,$round"
    rewards "$build,$round" "$round"
    kill -9 "$SERVER_PID"
    wait "$SERVER_PID" 2>/dev/null || true
    rm -rf "$WORK/data-run"
  done
done
