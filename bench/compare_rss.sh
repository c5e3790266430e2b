#!/bin/bash
# Footprint and restart of two server builds on the same data, alternating:
# a fleet of TRACES 256-d traces (the restart benchmark's shape: 4 robots,
# clusters of 10) is filled and its HNSW graph built and saved (index
# snapshot, clean stop) with B's build; then ROUNDS rounds each start A's
# server and B's on that data dir, timed until the port answers, and print
# the RSS 3 s after (the load is done when the port opens), the
# engine's snapshot load line and its split of the load (the store's read,
# then memory and index), with the store's, the memory image's, the
# reconcile's and the load's log lines as comment rows, and the snapshot
# saves (B's after the fill, A's at the end of round 0) and files' sizes. Each is stopped with kill -9
# (but A's first, below), so the snapshot
# on disk stays the one its build wrote. A's build must read B's snapshot
# layout: A's first start (round 0) loads B's snapshot and ends with a
# replay draw and a clean stop, which writes A's own for its later rounds.
# A starts on a copy of B's data dir: a newer A may migrate the store's
# layout (builds after 2026-11-30 do, once: round 0, A's first start, shows
# it), which B would no longer read.
#
#   bench/compare_rss.sh A_BUILD_DIR B_BUILD_DIR [TRACES] [ROUNDS]
#   (default: 200000 traces, 2 rounds)
# Environment: KEEP=DIR keeps the fill in DIR for the next run (its data
# dir as B's runs left it), WARM=1 reads the data dir into the page cache
# before each start (untimed), COLD=1 drops the page cache before each
# start instead (needs root: /proc/sys/vm/drop_caches), HNSW_CODES (int8 or float) sets the graph's codes of both,
# HNSW_FLOATS (file or memory) where int8 graphs keep their floats (the
# same build twice with each setting compares the two), SAVE=1 ends the
# last round's starts with a replay draw and a clean stop, whose snapshot
# saves it prints, A_WRAPPER runs A's servers under a command (e.g. "env
# GLIBC_TUNABLES=glibc.malloc.hugetlb=1", with A and B the same build).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 2 ]; then
  echo "usage: $0 A_BUILD_DIR B_BUILD_DIR [TRACES] [ROUNDS]" >&2
  exit 2
fi
a=$1
b=$2
traces=${3:-200000}
rounds=${4:-2}
# B's CLI waits for the graph: without it the wait would end at once and
# the snapshot hold a graph still linking.
for tool in "$a/bin/fleetmem-server" "$b/bin/fleetmem-server" "$b/bin/fleetmem"; do
  if [ ! -x "$tool" ]; then
    echo "$tool: no such executable (build it first)" >&2
    exit 2
  fi
done
if [ -n "${COLD:-}" ] && [ ! -w /proc/sys/vm/drop_caches ]; then
  echo "$0: COLD=1 drops the page cache: run it as root" >&2
  exit 2
fi
source "$here/tools/load/server_lib.sh"
bench_work compare-rss data-a
work=$WORK
fill_scale_fleet_once "$b" "$work" "$traces"

# save_line WHO LOG: the snapshot save LOG's server logged, as a comment row
# (its seconds, and how long uploads waited for it).
save_line() {
  grep -o 'index snapshot of [0-9]* codes saved in .*' "$2" | tail -1 |
    sed "s/^/# $1: /" || true
}
save_line "B's stop after the fill" "$work/build.log"

cp -a "$work/data" "$work/data-a"

payload_mib=$(awk -v n="$FILLED" 'BEGIN { print n * 1024 / 1048576 }')
echo "build,round,rss_mib,rss_over_payload,port_seconds,snapshot_load,store_read_s,memory_and_index_s"
for round in $(seq 0 "$rounds"); do
  for build in "$a" "$b"; do
    [ "$round" -gt 0 ] || [ "$build" = "$a" ] || continue
    data="$work/data"
    [ "$build" != "$a" ] || data="$work/data-a"
    # WARM: the data dir read into the page cache first, as on a host that
    # keeps it (this VM's pages out what goes unused for a minute).
    if [ -n "${WARM:-}" ]; then
      find "$data" -type f -exec cat {} + >/dev/null
    fi
    if [ -n "${COLD:-}" ]; then
      sync
      echo 3 >/proc/sys/vm/drop_caches
    fi
    wrapper=
    [ "$build" != "$a" ] || wrapper=${A_WRAPPER:-}
    start=$(date +%s.%N)
    SERVER_WRAPPER=$wrapper SERVER_START_SECONDS=1200 start_server "$build" \
      "$data" "$work/restart.log" --config "$work/restart.textproto"
    port_s=$(awk "BEGIN { printf \"%.2f\", $(date +%s.%N) - $start }")
    sleep 3
    rss=$(server_rss_mib "$SERVER_PID")
    load=$(sed -n 's/.*loaded from its index snapshot in \([0-9.]*\) s.*/\1 s/p' \
      "$work/restart.log")
    # The engine's own split: the store's read (the snapshot's beside it),
    # then memory and index.
    split=$(sed -n 's/.*store read \([0-9.]*\) s, memory and index \([0-9.]*\) s.*/\1,\2/p' \
      "$work/restart.log")
    awk -v b="$build" -v r="$round" -v m="$rss" -v p="$payload_mib" \
      -v s="$port_s" -v l="$load" -v x="${split:-,}" \
      'BEGIN { printf "%s,%d,%d,%.2f,%s,%s,%s\n", b, r, m, m / p, s,
               l == "" ? "rebuilt" : l, x }'
    # The store's split (records, codes, clusters) and the reconcile's.
    grep -o 'fleet "scale"\(: read [0-9]* trace records\|: index snapshot reconciled\|: [0-9]* traces in [0-9]* clusters taken\| loaded:\).*' \
      "$work/restart.log" | sed 's/^/# /' || true
    # The disk its graph holds beside the data dir (its floats' file).
    held=$(server_held_mib "$SERVER_PID")
    echo "# floats' file ${held% *} MiB, replaced snapshots held ${held#* } MiB"
    if [ "$round" -eq 0 ]; then
      # A's first start read B's snapshot; a replay draw (a write of the
      # store: the snapshot is no longer current) and a clean stop write
      # A's own (with a build that keeps one, the clusters' memory image
      # too, in A's layout), which A's later rounds load as after any clean
      # stop.
      "$b/bin/fleetmem" --server "$SERVER_ADDR" sample --fleet scale \
        --robot robot-0 --count 1000 >/dev/null
      stop_server
      save_line "A's stop" "$work/restart.log"
    elif [ -n "${SAVE:-}" ] && [ "$round" -eq "$rounds" ]; then
      # SAVE=1: the last round's servers each draw one replay sample (a
      # write of the store: the stop must save again) and stop cleanly, so
      # that both builds save the same fleet after the same start.
      "$b/bin/fleetmem" --server "$SERVER_ADDR" sample --fleet scale \
        --robot robot-0 --count 1000 >/dev/null
      stop_server
      save_line "$([ "$build" = "$a" ] && echo A || echo B)'s stop after a replay draw" \
        "$work/restart.log"
    else
      kill -9 "$SERVER_PID"
      wait "$SERVER_PID" 2>/dev/null || true
    fi
  done
done
# Each build's snapshot file on disk (A's written by its round 0's stop).
for dir in data-a data; do
  echo "# snapshot bytes in $dir: $(stat -c %s "$work/$dir"/db/index-snapshots/*.snapshot)"
done
