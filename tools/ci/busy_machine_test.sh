#!/usr/bin/env bash
# `make test` RUNS times in a row with a CPU burner (sha256sum /dev/zero) on
# every core beside it; prints each run's exit code and seconds
# (docs/testing.md, "Deterministic on a busy machine").
#
#   tools/ci/busy_machine_test.sh [RUNS]      (default 3)
set -uo pipefail
cd "$(dirname "$0")/../.."
runs=${1:-3}
failed=0
for i in $(seq 1 "$runs"); do
  burners=()
  for _ in $(seq 1 "$(nproc)"); do sha256sum /dev/zero & burners+=($!); done
  start=$SECONDS
  make test >"build/busy-machine-$i.log" 2>&1
  rc=$?
  kill "${burners[@]}" 2>/dev/null
  wait "${burners[@]}" 2>/dev/null
  echo "run $i: rc $rc, $((SECONDS - start)) s (log build/busy-machine-$i.log)"
  [ "$rc" = 0 ] || failed=1
done
exit "$failed"
