#!/usr/bin/env bash
# `make demo`'s whole path on a few frames (make test): the server, two
# fleetmem-robot processes per pass (the classical fleet, then the learning
# fleet with the metric head), the results table. The table's numbers are
# checked against what they must be for this input (tools/demo/check_demo.py):
# every row scores the same queries, recalls are counts over them, WR is
# recomputed from the per-robot rows, the learned row's map is every summer
# frame like the baseline's.
#
#   tools/demo/demo_smoke_test.sh BUILD_DIR
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
build=${1:-build}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
robots=2 frames=24
FLEETMEM_DEMO_DIR="$work" OMP_NUM_THREADS=1 \
  "$root/tools/demo/run_demo.sh" "$build" --robots "$robots" \
  --stretch-length "$frames" --segment-size 8 --fleet smoke \
  --sequential-robots >"$work/demo.log" 2>&1 || {
  tail -50 "$work/demo.log"
  exit 1
}
python3 "$root/tools/demo/check_demo.py" "$work/results.md" "$robots" "$frames"
