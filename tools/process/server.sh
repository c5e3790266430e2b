# The one way shell scripts start fleetmem-server (sourced, not run): the
# twin of tools/process/server_process.h. Waits for the server's readiness
# signal, its --ready-file (services/server/server_config.h), never for a
# log line or a fixed time.
#
# start_server BUILD DATA_DIR LOG [ARGS...]
#   Starts BUILD/bin/fleetmem-server --listen $SERVER_LISTEN --data-dir
#   DATA_DIR --ready-file LOG.ready ARGS..., its output in LOG, and returns
#   once it is ready. Sets SERVER_PID, SERVER_ADDR (the gRPC HOST:PORT),
#   SERVER_HTTP_ADDR (the HTTP HOST:PORT, empty without --http-listen).
#   Returns 1 with the log on stderr if the server exits first or is not
#   ready within SERVER_START_SECONDS.
# Environment: SERVER_LISTEN (127.0.0.1:0, a free port), SERVER_START_SECONDS
#   (60), SERVER_WRAPPER (e.g. "heaptrack -o FILE": the server runs under it
#   and SERVER_PID is the wrapper's).
start_server() {
  local build=$1 data=$2 log=$3
  shift 3
  local ready="$log.ready"
  rm -f "$ready"
  : >"$log"
  ${SERVER_WRAPPER:-} "$build/bin/fleetmem-server" \
    --listen "${SERVER_LISTEN:-127.0.0.1:0}" --data-dir "$data" \
    --ready-file "$ready" "$@" >>"$log" 2>&1 &
  SERVER_PID=$!
  SERVER_ADDR="" SERVER_HTTP_ADDR=""
  local deadline=$((SECONDS + ${SERVER_START_SECONDS:-60}))
  while [ "$SECONDS" -lt "$deadline" ]; do
    if [ -f "$ready" ]; then  # renamed into place: complete
      SERVER_ADDR=$(sed -n 's/^grpc=//p' "$ready")
      SERVER_HTTP_ADDR=$(sed -n 's/^http=//p' "$ready")
      return 0
    fi
    kill -0 "$SERVER_PID" 2>/dev/null || break
    sleep 0.05
  done
  echo "fleetmem-server was not ready (exited, or not within" \
    "${SERVER_START_SECONDS:-60} s); its log $log:" >&2
  tail -n 30 "$log" >&2
  return 1
}

# stop_server: SIGTERM to SERVER_PID, then its exit status must be 0.
stop_server() {
  kill -TERM "$SERVER_PID"
  local code=0
  wait "$SERVER_PID" || code=$?
  if [ "$code" != 0 ]; then
    echo "fleetmem-server exited with $code after SIGTERM" >&2
    return 1
  fi
}
