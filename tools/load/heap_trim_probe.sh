#!/usr/bin/env bash
# Is the heap's free memory a leak or memory malloc keeps? Asks a running
# fleetmem-server's C library to give its free heap pages back
# (malloc_trim(0), called through gdb: the server pauses for a moment) and
# prints RSS and the server's heap gauges (fleetmem_heap_bytes) before and
# after. Memory that malloc had kept comes back to the system; a leak would
# stay in "in_use". Needs gdb (apt-get install gdb) and ptrace rights over
# the server (root, or the same user with kernel.yama.ptrace_scope 0).
#
#   tools/load/heap_trim_probe.sh PID HTTP_HOST:PORT
set -euo pipefail
pid=$1
http=$2
sample() {
  local rss heap
  rss=$(sed -n 's/^VmRSS:[[:space:]]*\([0-9]*\).*/\1/p' "/proc/$pid/status")
  heap=$(curl -sS "http://$http/metrics" |
    sed -n 's/^fleetmem_heap_bytes{kind="\([a-z_]*\)"} \(.*\)/\1 \2/p' |
    awk '{printf "%s %.1f MiB  ", $1, $2 / 1048576}')
  echo "RSS $((rss / 1024)) MiB  heap: $heap"
}
echo "before: $(sample)"
gdb -batch -ex 'call (int) malloc_trim(0)' "/proc/$pid/exe" "$pid" >/dev/null 2>&1
echo "after malloc_trim(0): $(sample)"
