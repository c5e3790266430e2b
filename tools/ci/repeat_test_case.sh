#!/bin/bash
# Runs one gtest case of a test binary N times in a row, from copies of the
# binary and of the server it starts (so that a rebuild meanwhile changes
# nothing), and prints one line a run: passed or failed, seconds, and the
# lines the case prints that match SUMMARY (e.g. the cluster test's
# "served again" figures). Failed runs' output is kept in OUT_DIR.
#
#   tools/ci/repeat_test_case.sh BUILD_DIR TEST FILTER N OUT_DIR [SUMMARY]
#   e.g. tools/ci/repeat_test_case.sh build fleetmem_cluster_integration_test \
#          '*PausedReplica*' 50 /tmp/paused 'owner paused|NATS server killed'
# (docs/distributed.md, "The paused owner", was measured this way.)
set -uo pipefail
if [ $# -lt 5 ]; then
  sed -n '2,11p' "$0" >&2
  exit 2
fi
build=$1 test=$2 filter=$3 runs=$4 out=$5 summary=${6:-^$}
mkdir -p "$out"
cp "$build/tests/$test" "$build/bin/fleetmem-server" "$out/" || exit 2
export FLEETMEM_SERVER_BINARY="$out/fleetmem-server"
passed=0
for i in $(seq 1 "$runs"); do
  start=$(date +%s)
  if timeout 600 "$out/$test" --gtest_filter="$filter" >"$out/run-$i.log" 2>&1; then
    result=passed
    passed=$((passed + 1))
  else
    result=FAILED
  fi
  line=$(grep -E "$summary" "$out/run-$i.log" | tr -s ' ' | tr '\n' ' ')
  echo "run $i: $result $(( $(date +%s) - start )) s $line"
  [ "$result" = passed ] && rm -f "$out/run-$i.log"
done
echo "$passed of $runs passed"
