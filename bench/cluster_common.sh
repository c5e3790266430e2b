# Shared by the distributed-mode benchmarks (bench/cluster_*.sh): sourced
# after `build` is set. Makes a work directory ($work) removed on exit with
# the processes listed in `pids`, and defines start_nats, free_port and
# received.
nats=$(command -v nats-server || echo /usr/sbin/nats-server)
work=$(mktemp -d "/tmp/fleetmem-$(basename "$0" .sh)-XXXXXX")
pids=()
cleanup() {
  for pid in "${pids[@]}"; do kill -9 "$pid" 2>/dev/null || true; done
  [ -n "${KEEP_WORK:-}" ] && echo "kept $work" >&2 || rm -rf "$work"
}
trap cleanup EXIT

# start_nats DIR: a nats-server with JetStream under DIR/js on a free port
# (sets nats_port), returning once it accepts clients.
start_nats() {
  mkdir -p "$1/js"
  nats_port=$(free_port)
  "$nats" -a 127.0.0.1 -p "$nats_port" -js -sd "$1/js" >"$1/nats.log" 2>&1 &
  pids+=($!)
  for _ in $(seq 1 300); do
    grep -q "Listening for client connections" "$1/nats.log" && return 0
    sleep 0.1
  done
  echo "nats-server did not start; $1/nats.log:" >&2
  cat "$1/nats.log" >&2
  return 1
}

free_port() {
  python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'
}

# received FLEET ADDRESS: traces the fleet has received (its robots'), or -1.
received() {
  "$build/bin/fleetmem" --server "$2" --deadline-ms 2000 --json stats \
    --fleet "$1" 2>/dev/null |
    python3 -c 'import json,sys
try:
    s = json.loads(sys.stdin.read())
    print(sum(int(r.get("received", 0)) for r in s.get("robots", [])))
except Exception:
    print(-1)'
}
