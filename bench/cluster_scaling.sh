#!/usr/bin/env bash
# Distributed mode's scaling on this host (docs/distributed.md): ingest and
# query with 1, 2 and 3 fleetmem-server replicas on one nats-server with
# JetStream, FLEETS fleets of 256-d traces, each fleet's robots uploading
# through replica (fleet mod R) with fleetmem-load; and the embedded mode
# (one server, no NATS: "embedded" below) under the same load, as the peer.
#
# For each R it reports:
#   ingest      traces/s acknowledged (appended to the fleets' logs) in all
#   applied     traces/s materialised: every acknowledged trace received by
#               its fleet's owner, from the uploads' start (the embedded
#               mode applies before it acknowledges)
#   query p50/p99  QueryPlace through replica 0 on every fleet in turn
#               (fleetmem-load bench on the fleet, no uploads), in ms;
#               replica 0 forwards the fleets others own
# and each as a ratio to the embedded mode, measured in the same run.
#
#   bench/cluster_scaling.sh [BUILD_DIR] [OUT_FILE]
# Environment: FLEETS (6), ROBOTS per fleet (2), SECONDS of upload (10),
# REPLICAS ("1 2 3").
set -euo pipefail
build=$(cd "${1:-build}" && pwd)
out=${2:-/dev/stdout}
fleets=${FLEETS:-6}
robots=${ROBOTS:-2}
seconds=${SECONDS_UPLOAD:-10}
replica_counts=${REPLICAS:-"embedded 1 2 3"}
source "$(dirname "$0")/cluster_common.sh"
source "$(dirname "$0")/../tools/process/server.sh"

results=()
for r in $replica_counts; do
  dir="$work/r$r"
  mkdir -p "$dir/js"
  addresses=()
  if [ "$r" = embedded ]; then
    port=$(free_port)
    SERVER_LISTEN=127.0.0.1:$port start_server "$build" "$dir/replica-0" \
      "$dir/replica-0.log"
    pids+=("$SERVER_PID")
    addresses+=("127.0.0.1:$port")
    r=1
  else
    start_nats "$dir"
    echo 'cluster { replicas: 1 }' >"$dir/replica.textproto"
    for i in $(seq 0 $((r - 1))); do
      port=$(free_port)
      SERVER_LISTEN=127.0.0.1:$port start_server "$build" "$dir/replica-$i" \
        "$dir/replica-$i.log" --cluster "nats://127.0.0.1:$nats_port" \
        --advertise "127.0.0.1:$port" --config "$dir/replica.textproto"
      pids+=("$SERVER_PID")
      addresses+=("127.0.0.1:$port")
    done
  fi
  label=$r
  [ -f "$dir/nats.log" ] || label=embedded
  # Ingest: every fleet's robots at once, each fleet through one replica.
  start=$(date +%s.%N)
  upload_pids=()
  for f in $(seq 0 $((fleets - 1))); do
    "$build/bin/fleetmem-load" upload --server "${addresses[$((f % r))]}" \
      --fleet "fleet-$f" --dimension 256 --robots "$robots" --batch 100 \
      --seconds "$seconds" >"$dir/upload-$f.txt" 2>&1 &
    upload_pids+=($!)
  done
  for pid in "${upload_pids[@]}"; do wait "$pid"; done
  acked_total=0
  ingest=0
  for f in $(seq 0 $((fleets - 1))); do
    line=$(grep '^acknowledged' "$dir/upload-$f.txt")
    acked=$(echo "$line" | awk '{print $2}')
    rate=$(echo "$line" | sed 's/.*(\([0-9.]*\)\/s).*/\1/')
    acked_total=$((acked_total + acked))
    ingest=$(python3 -c "print($ingest + $rate)")
    eval "acked_$f=$acked"
  done
  # Applied: until every fleet's owner has received what was acknowledged.
  for f in $(seq 0 $((fleets - 1))); do
    want=$(eval echo "\$acked_$f")
    for _ in $(seq 1 1200); do
      [ "$(received "fleet-$f" "${addresses[0]}")" = "$want" ] && break
      sleep 0.25
    done
  done
  applied_s=$(python3 -c "import time; print(time.time() - $start)")
  applied=$(python3 -c "print($acked_total / $applied_s)")

  # Queries through replica 0 on every fleet (forwarded to other owners).
  p50s=()
  p99s=()
  for f in $(seq 0 $((fleets - 1))); do
    "$build/bin/fleetmem-load" bench --server "${addresses[0]}" \
      --fleet "fleet-$f" --dimension 256 --robots 0 --query-rate 200 \
      --seconds 3 >"$dir/query-$f.txt" 2>/dev/null
    row=$(grep '^fleetmem ' "$dir/query-$f.txt")
    p50s+=("$(echo "$row" | awk '{print $6}')")
    p99s+=("$(echo "$row" | awk '{print $7}')")
  done
  query=$(python3 -c "import statistics as s; a=[float(x) for x in '${p50s[*]}'.split()]; b=[float(x) for x in '${p99s[*]}'.split()]; print(f'{s.median(a):.3f} {s.median(b):.3f}')")
  results+=("$label $ingest $applied $query $acked_total")
  for pid in "${pids[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
  wait 2>/dev/null || true
  pids=()
  sleep 1
done

{
  echo "# bench/cluster_scaling.sh: $fleets fleets x $robots robots, 256-d,"
  echo "# batches of 100, $seconds s of uploads; one nats-server; $(nproc) cores"
  printf '%-8s %12s %8s %12s %8s %10s %10s %10s\n' replicas "ingest/s" ratio \
    "applied/s" ratio "query p50" "query p99" traces
  base_ingest=""
  base_applied=""
  for row in "${results[@]}"; do
    read -r r ingest applied p50 p99 traces <<<"$row"
    base_ingest=${base_ingest:-$ingest}
    base_applied=${base_applied:-$applied}
    printf '%-8s %12.0f %8.2f %12.0f %8.2f %10s %10s %10s\n' "$r" "$ingest" \
      "$(python3 -c "print($ingest / $base_ingest)")" "$applied" \
      "$(python3 -c "print($applied / $base_applied)")" "$p50" "$p99" "$traces"
  done
  echo "# query p50/p99: median over the fleets of fleetmem-load bench's"
  echo "# QueryPlace latency (ms) through replica 0; ratios against the"
  echo "# first row"
} >"$out"
