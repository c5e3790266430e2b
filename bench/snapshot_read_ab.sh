#!/bin/bash
# One build's restart from the same index snapshot in its two file formats,
# alternating (issue 49, sixth round): the format of 2026-12-01
# ("FMIDXSN2", a checksum per 8 MiB chunk, checked as the load reads it:
# the file is read once) against the first ("FMIDXSN1", one checksum of the
# whole file, checked before the load reads it), which the build still
# reads. The restart benchmark's fleet of N 256-d traces is filled
# (fill_scale_fleet), its graph built and saved by a clean stop; a copy of
# the data dir gets the snapshot rewritten in the first format
# (bench/snapshot_to_v1.py: the same payload, one checksum); then ROUNDS
# rounds start the server on each copy, timed until the port answers, and
# print the engine's load lines. Each start is stopped with kill -9, so
# each snapshot stays as it is.
#
#   bench/snapshot_read_ab.sh [BUILD_DIR] [N] [ROUNDS]
#   (default: build 1000000 3)
# Environment: HNSW_CODES, HNSW_FLOATS (as bench/compare_rss.sh), KEEP (a
# directory: the filled data dir is kept there and reused by the next run
# with the same KEEP, which then skips the fill).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
n=${2:-1000000}
rounds=${3:-3}
source "$here/tools/load/server_lib.sh"
bench_work snapshot-ab v1 v2
work=$WORK
fill_scale_fleet_once "$build" "$work" "$n"
rm -rf "$work/v1" "$work/v2"
cp -a "$work/data" "$work/v2"
cp -a "$work/data" "$work/v1"
for file in "$work"/v1/db/index-snapshots/*.snapshot; do
  /usr/bin/python3 "$here/bench/snapshot_to_v1.py" "$file"
done
echo "format,round,port_seconds,store_read_s,memory_and_index_s,handles_s,index_s"
for round in $(seq 1 "$rounds"); do
  for format in v2 v1; do
    start=$(date +%s.%N)
    SERVER_START_SECONDS=1200 start_server "$build" "$work/$format" \
      "$work/restart.log" --config "$work/restart.textproto"
    port_s=$(awk "BEGIN { printf \"%.2f\", $(date +%s.%N) - $start }")
    split=$(sed -n 's/.*store read \([0-9.]*\) s, memory and index \([0-9.]*\) s.*/\1,\2/p' \
      "$work/restart.log")
    beside=$(sed -n 's/.*(handles \([0-9.e-]*\) s and index \([0-9.e-]*\) s beside.*/\1,\2/p' \
      "$work/restart.log")
    echo "$format,$round,$port_s,${split:-,},${beside:-,}"
    grep -o 'fleet "scale": \(read [0-9]* trace records\|index snapshot reconciled\|rebuilding\).*' \
      "$work/restart.log" | sed 's/^/# /' || true
    kill -9 "$SERVER_PID"
    wait "$SERVER_PID" 2>/dev/null || true
  done
done
