#!/usr/bin/env bash
# Runs the Nordland fleet demo end to end (`make demo`):
#   1. starts BUILD_DIR/bin/fleetmem-server on a free local port with its
#      embedded RocksDB under .demo/data (logs in .demo/server.log),
#   2. waits until it is ready (its --ready-file, tools/process/server.sh),
#   3. runs BUILD_DIR/bin/fleetmem-demo against it, which runs the fleet as
#      fleetmem-robot processes (their data dirs under .demo/robots) and
#      prints the results table (also in .demo/results.md),
#   4. stops the server with SIGTERM and waits for it (also on failure or
#      Ctrl-C, through an exit trap).
#
# Usage: tools/demo/run_demo.sh [BUILD_DIR] [fleetmem-demo flags...]
#   BUILD_DIR defaults to "build" (relative to the project root).
# Environment: FLEETMEM_DEMO_STARTUP_TIMEOUT (seconds, default 30),
#   FLEETMEM_DEMO_STOP_TIMEOUT (seconds, default 30), FLEETMEM_DEMO_GPL=1
#   (add the GPL model's rows), FLEETMEM_DEMO_SERVER_ARGS (more server
#   flags), FLEETMEM_DEMO_DIR (instead of .demo/).
set -euo pipefail

root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
build_dir="${1:-build}"
if [[ $# -gt 0 ]]; then shift; fi
case "$build_dir" in
  /*) ;;
  *) build_dir="$root/$build_dir" ;;
esac
server_bin="$build_dir/bin/fleetmem-server"
demo_bin="$build_dir/bin/fleetmem-demo"
robot_bin="$build_dir/bin/fleetmem-robot"
for bin in "$server_bin" "$demo_bin" "$robot_bin"; do
  if [[ ! -x "$bin" ]]; then
    echo "run_demo.sh: $bin not found; build it first (make build)" >&2
    exit 1
  fi
done

demo_dir="${FLEETMEM_DEMO_DIR:-$root/.demo}"
log="$demo_dir/server.log"
results="$demo_dir/results.md"
startup_timeout="${FLEETMEM_DEMO_STARTUP_TIMEOUT:-30}"
stop_timeout="${FLEETMEM_DEMO_STOP_TIMEOUT:-30}"
mkdir -p "$demo_dir"

server_pid=""
server_status=0
# Stops the server (SIGTERM, then SIGKILL after stop_timeout) and records
# its exit status in server_status. Safe to call twice.
stop_demo_server() {
  [[ -n "$server_pid" ]] || return 0
  local pid="$server_pid"
  server_pid=""
  if kill -0 "$pid" 2>/dev/null; then
    echo "run_demo.sh: stopping fleetmem-server (pid $pid)"
    kill -TERM "$pid" 2>/dev/null || true
    local waited=0
    while kill -0 "$pid" 2>/dev/null && ((waited < stop_timeout * 10)); do
      sleep 0.1
      waited=$((waited + 1))
    done
    if kill -0 "$pid" 2>/dev/null; then
      echo "run_demo.sh: fleetmem-server did not stop within" \
        "${stop_timeout}s of SIGTERM; killing it" >&2
      kill -KILL "$pid" 2>/dev/null || true
    fi
  fi
  server_status=0
  wait "$pid" 2>/dev/null || server_status=$?
}
demo_pid=""
# On Ctrl-C or SIGTERM: stop the demo too (it runs in the background so that
# the signal is handled at once), then exit; the EXIT trap stops the server.
stop_all() {
  if [[ -n "$demo_pid" ]]; then
    kill -TERM "$demo_pid" 2>/dev/null || true
    wait "$demo_pid" 2>/dev/null || true
    demo_pid=""
  fi
  exit "$1"
}
trap stop_demo_server EXIT
trap 'stop_all 130' INT
trap 'stop_all 143' TERM

# Port 0: the server picks a free port; its ready file gives the address.
# The HTTP port (dashboard, REST, metrics): FLEETMEM_DEMO_HTTP_PORT, else a
# free port, printed below.
# shellcheck source=../process/server.sh
source "$root/tools/process/server.sh"
echo "run_demo.sh: starting fleetmem-server, log $log"
# FLEETMEM_DEMO_SERVER_ARGS: more server flags, e.g. "--config FILE" for
# other memory options (docs/results.md compares forgetting by merging and
# by dropping this way).
# shellcheck disable=SC2086
if ! SERVER_START_SECONDS=$startup_timeout start_server "$build_dir" \
  "$demo_dir/data" "$log" \
  --http-listen "127.0.0.1:${FLEETMEM_DEMO_HTTP_PORT:-0}" \
  ${FLEETMEM_DEMO_SERVER_ARGS:-}; then
  kill -KILL "$SERVER_PID" 2>/dev/null || true
  echo "run_demo.sh: fleetmem-server did not start" >&2
  exit 1
fi
server_pid=$SERVER_PID
address=$SERVER_ADDR
http_address=$SERVER_HTTP_ADDR
echo "run_demo.sh: fleetmem-server (pid $server_pid) listening on $address"
echo "run_demo.sh: watch the fleet's memory live at http://$http_address/#unit=route%20index"

# The learned row is the robots' default learner, the metric head on the
# HOG code (fleetmem-demo --learn). FLEETMEM_DEMO_GPL=1 adds the GPL
# model's rows: its encoder pre-trained once on the first summer stretch
# (300 frames, quick settings), then frozen; kept in .demo/ and reused.
gpl_args=()
if [[ "${FLEETMEM_DEMO_GPL:-0}" == 1 ]]; then
  eval_bin="$build_dir/bin/fleetmem-eval"
  gpl_model="$demo_dir/gpl-fleet.pt"
  if [[ ! -f "$gpl_model" ]]; then
    echo "run_demo.sh: pre-training the fleet's GPL model on 300 summer frames (about a minute)"
    "$eval_bin" pretrain --images "${FLEETMEM_DATA:-$root/../shared/data}/nordland/summer" \
      --count 300 --steps 300 --version gpl-demo-64x32-d256-v1 --out "$gpl_model"
  fi
  gpl_args=(--gpl-model "$gpl_model")
fi

demo_status=0
"$demo_bin" --server "$address" --results-md "$results" \
  --robot-binary "$robot_bin" --work-dir "$demo_dir/robots" \
  "${gpl_args[@]}" "$@" &
demo_pid=$!
wait "$demo_pid" || demo_status=$?
demo_pid=""

stop_demo_server
if ((server_status != 0)); then
  echo "run_demo.sh: fleetmem-server exited with status $server_status;" \
    "see $log" >&2
fi
if ((demo_status != 0)); then
  echo "run_demo.sh: fleetmem-demo failed (status $demo_status)" >&2
  exit "$demo_status"
fi
if ((server_status != 0)); then exit 1; fi
echo "run_demo.sh: done; results in $results, server log in $log"
