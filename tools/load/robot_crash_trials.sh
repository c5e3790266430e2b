#!/usr/bin/env bash
# Robot crash trials: TRIALS times, a camera robot (real Nordland summer
# frames) and a laser robot (the real ACES log) observe and upload, each to
# its own fleet, while the server and the robots are killed with SIGKILL at
# random moments (KILLS per trial; each kill picks the server or one robot)
# and restarted on the same data dirs and port. When both robots have
# finished (exit 0: source observed, queue drained), the server must hold
# each robot's traces exactly once: RECEIVED == MAX SEQ == observations
# (`fleetmem stats`). Prints one line per trial; exits 1 on any loss or
# repeat.
#
#   tools/load/robot_crash_trials.sh [BUILD_DIR] [TRIALS]   (make robot-crash)
# Environment: ROBOT_CRASH_KILLS (4), ROBOT_CRASH_CAMERA (1500 frames),
#   ROBOT_CRASH_LASER (3000 scans), FLEETMEM_DATA (../shared/data).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
build=${1:-build}
trials=${2:-10}
kills=${ROBOT_CRASH_KILLS:-4}
camera_n=${ROBOT_CRASH_CAMERA:-1500}
laser_n=${ROBOT_CRASH_LASER:-3000}
data=${FLEETMEM_DATA:-$root/../shared/data}
dir=$(mktemp -d "${TMPDIR:-/tmp}/fleetmem-robot-crash-XXXXXX")
server_pid="" camera_pid="" laser_pid="" server_starts=0
trap 'kill -9 $server_pid $camera_pid $laser_pid 2>/dev/null || true; rm -rf "$dir"' EXIT
RANDOM=7  # repeatable kill times

# shellcheck source=../process/server.sh
source "$root/tools/process/server.sh"
# The first start picks a free port; every restart keeps it, so the robots
# find the server again.
addr=""
restart_server() {
  SERVER_LISTEN=${addr:-127.0.0.1:0} start_server "$build" "$dir/server" \
    "$dir/server-$((++server_starts)).log" || return 1
  server_pid=$SERVER_PID
  addr=$SERVER_ADDR
}
# start_robot NAME FLEET SOURCE LAST RATE: sets ${NAME}_pid.
start_robot() {
  "$build/bin/fleetmem-robot" --server "$addr" --fleet "$2-$trial" \
    --robot-id "$1" --source "$3" --data-dir "$dir/$1-$trial" --last "$4" \
    --rate "$5" --segment-size 100 --drain-timeout 120 \
    >>"$dir/$1-$trial.log" 2>&1 &
  eval "$1_pid=$!"
}
start_camera() { start_robot camera camera "nordland:$data/nordland/summer" "$camera_n" 250; }
start_laser() { start_robot laser laser "carmen:$data/laser/aces.clf.bz2" "$laser_n" 500; }
# check FLEET ROBOT N: prints "received/max_seq" and fails unless both are N.
check() {
  local line
  line=$("$build/bin/fleetmem" --server "$addr" stats --fleet "$1" |
    awk -v r="$2" '$1 == r {print $5 "/" $4}')
  echo "$line"
  [ "$line" = "$3/$3" ]
}

mkdir -p "$dir/server"
restart_server
failed=0
printf '%5s %-28s %18s %18s %s\n' trial kills "camera recv/max" "laser recv/max" result
for trial in $(seq 1 "$trials"); do
  start_camera
  start_laser
  done_kills=""
  for _ in $(seq 1 "$kills"); do
    sleep "$(awk -v ms=$((500 + RANDOM % 2500)) 'BEGIN {print ms / 1000}')"
    case $((RANDOM % 3)) in
      0) kill -9 "$server_pid"; wait "$server_pid" 2>/dev/null || true
         sleep "$(awk -v ms=$((RANDOM % 1500)) 'BEGIN {print ms / 1000}')"
         restart_server; done_kills="$done_kills server" ;;
      1) kill -9 "$camera_pid" 2>/dev/null || true
         wait "$camera_pid" 2>/dev/null || true
         start_camera; done_kills="$done_kills camera" ;;
      2) kill -9 "$laser_pid" 2>/dev/null || true
         wait "$laser_pid" 2>/dev/null || true
         start_laser; done_kills="$done_kills laser" ;;
    esac
  done
  camera_status=0 laser_status=0
  wait "$camera_pid" || camera_status=$?
  wait "$laser_pid" || laser_status=$?
  camera_pid="" laser_pid=""
  result=ok
  camera=$(check "camera-$trial" camera "$camera_n") || result=FAILED
  laser=$(check "laser-$trial" laser "$laser_n") || result=FAILED
  if [ "$camera_status" != 0 ] || [ "$laser_status" != 0 ]; then
    result="FAILED (robot exit $camera_status/$laser_status)"
  fi
  [ "$result" = ok ] || failed=1
  printf '%5d %-28s %18s %18s %s\n' "$trial" "${done_kills# }" "$camera" \
    "$laser" "$result"
done
kill -TERM "$server_pid"; wait "$server_pid" || true
if [ "$failed" != 0 ]; then
  echo "robot crash trials: traces LOST or stored twice; logs in $dir" >&2
  trap - EXIT
  exit 1
fi
echo "robot crash trials: $trials trials x $kills SIGKILLs of the server or a robot; every observation stored exactly once"
