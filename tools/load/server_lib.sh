# Shell helpers for the crash and soak scripts (sourced, not run).

# start_server BUILD DATA_DIR LOG [ARGS...]: starts fleetmem-server on a free
# loopback port; sets SERVER_PID and SERVER_ADDR. With SERVER_WRAPPER set
# (e.g. "heaptrack -o FILE") the server runs under it and SERVER_PID is the
# wrapper's; SERVER_START_TRIES tenths of a second are waited for the port
# (300 unless set).
start_server() {
  local build=$1 data=$2 log=$3
  shift 3
  : >"$log"  # exists before the server's shell opens it
  ${SERVER_WRAPPER:-} "$build/bin/fleetmem-server" --listen 127.0.0.1:0 \
    --data-dir "$data" "$@" >"$log" 2>&1 &
  SERVER_PID=$!
  for _ in $(seq 1 "${SERVER_START_TRIES:-300}"); do
    SERVER_ADDR=$(sed -n 's/^fleetmem-server listening on \(.*\)$/\1/p' "$log" | head -1 || true)
    [ -n "$SERVER_ADDR" ] && return 0
    kill -0 "$SERVER_PID" 2>/dev/null || break
    sleep 0.1
  done
  echo "fleetmem-server did not start; its log:" >&2
  cat "$log" >&2
  return 1
}

# stop_server: SIGTERM, then the exit status must be 0.
stop_server() {
  kill -TERM "$SERVER_PID"
  local code=0
  wait "$SERVER_PID" || code=$?
  if [ "$code" != 0 ]; then
    echo "fleetmem-server exited with $code after SIGTERM" >&2
    return 1
  fi
}

# unindexed_codes BUILD FLEET: the fleet's codes outside the HNSW graph
# (GetStats unindexed_codes; protobuf JSON leaves a zero out).
unindexed_codes() {
  local n
  n=$("$1/bin/fleetmem" --server "$SERVER_ADDR" --json stats --fleet "$2" |
    sed -n 's/.*"unindexedCodes":"\{0,1\}\([0-9]*\).*/\1/p')
  echo "${n:-0}"
}

# fill_scale_fleet BUILD WORK TRACES: the restart and footprint benchmarks'
# fleet. Writes WORK/fill.textproto (the exact index) and
# WORK/restart.textproto (no periodic snapshot: the snapshot a restart
# starts from is the one the previous stop wrote), both with limits for
# TRACES traces in clusters of 10 (also left in LIMITS), and fills fleet
# "scale" on WORK/data with TRACES 256-d traces (4 robots, batches of 200),
# printing the load generator's summary. FILLED is the traces acknowledged
# (whole batches: a little more than TRACES).
fill_scale_fleet() {
  local build=$1 work=$2 traces=$3
  LIMITS="memory { max_clusters: $((traces / 10 + 100)) }
limits { max_traces_per_fleet: $((traces * 2)) }"
  printf 'index: "exact"\n%s\n' "$LIMITS" >"$work/fill.textproto"
  printf 'index_snapshot_interval_seconds: 0\n%s\n' "$LIMITS" \
    >"$work/restart.textproto"
  start_server "$build" "$work/data" "$work/fill.log" \
    --config "$work/fill.textproto"
  local summary
  summary=$("$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" \
    --fleet scale --dimension 256 --robots 4 --batch 200 --seconds 100000 \
    --traces "$traces" | tail -1)
  echo "$summary"
  FILLED=$(sed -n 's/^acknowledged \([0-9]*\) traces.*/\1/p' <<<"$summary")
  stop_server
}

# server_rss_mib PID: the resident set of fleetmem-server PID, or of the
# fleetmem-server child of PID (a wrapper's), in MiB.
server_rss_mib() {
  local pid
  pid=$(pgrep -P "$1" -f fleetmem-server || echo "$1")
  echo $(( $(ps -o rss= -p "$pid") / 1024 ))
}
