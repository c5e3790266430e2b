# Shell helpers for the crash and soak scripts (sourced, not run).

# start_server BUILD DATA_DIR LOG [ARGS...]: starts fleetmem-server on a free
# loopback port; sets SERVER_PID and SERVER_ADDR.
start_server() {
  local build=$1 data=$2 log=$3
  shift 3
  : >"$log"  # exists before the server's shell opens it
  "$build/bin/fleetmem-server" --listen 127.0.0.1:0 --data-dir "$data" "$@" \
    >"$log" 2>&1 &
  SERVER_PID=$!
  for _ in $(seq 1 300); do
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
