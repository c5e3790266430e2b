#!/usr/bin/env bash
# Crash trials: TRIALS times, robots upload concurrently while the server is
# killed with SIGKILL at a random moment; after each restart every trace the
# server ever acknowledged (in any trial) is re-sent and must come back as a
# duplicate. The server acknowledges at the durable append to the fleet's
# log and applies behind it; the server logs of the trial and of its
# restart must hold no entry applied twice (the applier logs one if an
# entry's traces were applied before). Prints one line per trial and exits
# 1 if anything was lost or applied twice.
#
#   tools/load/crash_trials.sh [BUILD_DIR] [TRIALS]      (make crash)
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
source "$here/server_lib.sh"
build=${1:-build}
trials=${2:-20}
robots=${CRASH_ROBOTS:-4}
dir=$(mktemp -d "${TMPDIR:-/tmp}/fleetmem-crash-XXXXXX")
trap 'kill -9 ${SERVER_PID:-0} 2>/dev/null || true; rm -rf "$dir"' EXIT
ack="$dir/acknowledged.log"
: >"$ack"
load="$build/bin/fleetmem-load"
RANDOM=42  # repeatable kill times

printf '%5s %8s %13s %13s %6s %6s %s\n' trial kill_ms acknowledged cumulative lost twice verify
lost_total=0
for trial in $(seq 1 "$trials"); do
  start_server "$build" "$dir/data" "$dir/server-$trial.log"
  before=$(awk '{n += $3 - $2 + 1} END {print n + 0}' "$ack")
  "$load" upload --server "$SERVER_ADDR" --robots "$robots" --batch 50 \
    --seconds 60 --first-seq $((trial * 1000000)) --ack-log "$ack" \
    --stop-on-error >"$dir/load-$trial.log" 2>&1 &
  load_pid=$!
  kill_ms=$((300 + RANDOM % 2200))
  sleep "$(awk -v ms="$kill_ms" 'BEGIN {print ms / 1000}')"
  kill -9 "$SERVER_PID"
  wait "$SERVER_PID" 2>/dev/null || true
  wait "$load_pid" || true
  after=$(awk '{n += $3 - $2 + 1} END {print n + 0}' "$ack")
  # Restart in place and check every trace acknowledged so far.
  start_server "$build" "$dir/data" "$dir/server-$trial-check.log"
  if result=$("$load" verify --server "$SERVER_ADDR" --ack-log "$ack" 2>&1); then
    lost=0
  else
    lost=$(echo "$result" | sed -n 's/.*lost \([0-9]*\).*/\1/p')
    lost=${lost:-?}
    lost_total=1
  fi
  stop_server
  twice=$(cat "$dir/server-$trial.log" "$dir/server-$trial-check.log" |
    grep -c "applied twice" || true)
  [ "$twice" = 0 ] || lost_total=1
  printf '%5d %8d %13d %13d %6s %6s %s\n' "$trial" "$kill_ms" \
    $((after - before)) "$after" "$lost" "$twice" "$result"
done
if [ "$lost_total" != 0 ]; then
  echo "crash trials: acknowledged traces were LOST or applied twice" >&2
  exit 1
fi
echo "crash trials: $trials SIGKILLs under load of $robots robots; every acknowledged trace is stored, none applied twice"
