#!/bin/bash
# Upload throughput of two server builds, measured alternately in one run so
# that both see the same machine state (this VM's fsync and CPU rates drift
# by tens of percent between minutes): ROUNDS rounds of 6 s of
# `fleetmem-load upload` (256-d traces, batches of 200, default server
# settings, an empty data directory each time) with 1 and with 8 streams,
# against A's server, then B's. Prints every round and the medians.
#
#   bench/compare_builds.sh A_BUILD_DIR B_BUILD_DIR [ROUNDS]
#
# A build directory is one with bin/fleetmem-server, e.g. a worktree of an
# earlier commit built with `cmake -S . -B build && ninja -C build
# fleetmem-server`. The load generator is B's. Both servers must take
# --ready-file (the readiness signal tools/process/server.sh waits for).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 2 ]; then
  echo "usage: $0 A_BUILD_DIR B_BUILD_DIR [ROUNDS]" >&2
  exit 2
fi
a=$1
b=$2
rounds=${3:-3}
for dir in "$a" "$b"; do
  if [ ! -x "$dir/bin/fleetmem-server" ]; then
    echo "$dir/bin/fleetmem-server: no such executable (build it first)" >&2
    exit 2
  fi
done
if ! [[ $rounds =~ ^[1-9][0-9]*$ ]]; then
  echo "ROUNDS must be a positive integer, not '$rounds'" >&2
  exit 2
fi
work=$(mktemp -d)
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
median() { sort -n | awk '{v[NR] = $1} END {print v[int((NR + 1) / 2)]}'; }
for streams in 1 8; do
  : >"$work/a.txt"
  : >"$work/b.txt"
  for round in $(seq 1 "$rounds"); do
    for side in a b; do
      dir=$a
      [ $side = b ] && dir=$b
      rm -rf "$work/data"
      start_server "$dir" "$work/data" "$work/server.log"
      rate=$("$b/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet cmp \
        --dimension 256 --robots "$streams" --batch 200 --seconds 6 |
        tail -1 | sed -n 's/.*(\([0-9]*\)\/s).*/\1/p')
      stop_server
      echo "$rate" >>"$work/$side.txt"
      echo "streams $streams round $round $side: $rate traces/s"
    done
  done
  ma=$(median <"$work/a.txt")
  mb=$(median <"$work/b.txt")
  echo "streams $streams median: A $ma, B $mb traces/s, B/A $(awk -v a="$ma" -v b="$mb" 'BEGIN {printf "%.2f", b / a}')"
done
