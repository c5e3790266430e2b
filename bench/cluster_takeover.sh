#!/usr/bin/env bash
# Distributed mode: how long a replica with an empty store takes to serve a
# fleet whose owner stops, with snapshots (restore the latest, apply the
# tail) and without (apply the whole log); docs/distributed.md.
#
# One nats-server; replica A owns one fleet of 256-d traces uploaded by
# fleetmem-load (TRACES in batches of 100, 2 robots) and applies them all;
# replica B starts with an empty store; A stops cleanly (SIGTERM: it hands
# its lease over) and the clock runs until B answers the fleet's stats with
# every trace received. Per setting of cluster.snapshot_every_entries
# (SNAPSHOTS, "0 1000 250": 0 = no snapshots) it reports the takeover time and
# the log entry through which B restored a snapshot, if it did.
#
#   bench/cluster_takeover.sh [BUILD_DIR] [OUT_FILE]
set -euo pipefail
build=$(cd "${1:-build}" && pwd)
out=${2:-/dev/stdout}
traces=${TRACES:-200000}
settings=${SNAPSHOTS:-"0 1000 250"}
source "$(dirname "$0")/cluster_common.sh"
source "$(dirname "$0")/../tools/process/server.sh"
# start NAME PORT: a replica on the run's nats-server.
start() {
  echo "cluster { replicas: 1 snapshot_every_entries: $snap }" \
    >"$dir/$1.textproto"
  SERVER_LISTEN=127.0.0.1:$2 start_server "$build" "$dir/$1" "$dir/$1.log" \
    --cluster "nats://127.0.0.1:$nats_port" --advertise "127.0.0.1:$2" \
    --config "$dir/$1.textproto" || exit 1
  pids+=("$SERVER_PID")
  last_pid=$SERVER_PID
}

rows=()
for snap in $settings; do
  dir="$work/s$snap"
  mkdir -p "$dir/js"
  start_nats "$dir"
  port_a=$(free_port)
  start a "$port_a"
  pid_a=$last_pid
  "$build/bin/fleetmem-load" upload --server "127.0.0.1:$port_a" --fleet f \
    --dimension 256 --robots 2 --batch 100 --traces "$traces" \
    --seconds 600 >"$dir/upload.txt" 2>&1
  acked=$(grep '^acknowledged' "$dir/upload.txt" | awk '{print $2}')
  for _ in $(seq 1 2400); do
    [ "$(received f "127.0.0.1:$port_a")" = "$acked" ] && break
    sleep 0.25
  done
  port_b=$(free_port)
  start b "$port_b"
  sleep 1
  t0=$(date +%s.%N)
  kill -TERM "$pid_a"
  for _ in $(seq 1 12000); do
    [ "$(received f "127.0.0.1:$port_b")" = "$acked" ] && break
    sleep 0.05
  done
  took=$(python3 -c "import time; print(f'{time.time() - $t0:.2f}')")
  restored=$(grep -o 'restored from its snapshot through entry [0-9]*' \
    "$dir/b.log" | grep -o '[0-9]*$' || true)
  rows+=("$snap $acked $took ${restored:-none}")
  for pid in "${pids[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
  pids=()
done

{
  echo "# bench/cluster_takeover.sh: one fleet, $traces 256-d traces in batches"
  echo "# of 100 (about $((traces / 100)) log entries); one nats-server; $(nproc) cores"
  printf '%-22s %10s %12s %22s\n' snapshot_every_entries traces "takeover s" \
    "restored through entry"
  for row in "${rows[@]}"; do
    read -r snap acked took restored <<<"$row"
    printf '%-22s %10s %12s %22s\n' "$snap" "$acked" "$took" "$restored"
  done
} >"$out"
