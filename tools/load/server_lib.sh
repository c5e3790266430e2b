# Shell helpers for the crash and soak scripts (sourced, not run).

# start_server and stop_server: the project's one shell helper.
# shellcheck source=../process/server.sh
source "$(dirname "${BASH_SOURCE[0]}")/../process/server.sh"

# unindexed_codes BUILD FLEET: the fleet's codes outside the HNSW graph
# (GetStats unindexed_codes; protobuf JSON leaves a zero out).
unindexed_codes() {
  local n
  n=$("$1/bin/fleetmem" --server "$SERVER_ADDR" --json stats --fleet "$2" |
    sed -n 's/.*"unindexedCodes":"\{0,1\}\([0-9]*\).*/\1/p')
  echo "${n:-0}"
}

# backlog_traces BUILD FLEET: the fleet's traces acknowledged and not
# applied (GetStats backlog_traces; 0 where the server does not say: a
# build before the write path applies before it acknowledges).
backlog_traces() {
  local n
  n=$("$1/bin/fleetmem" --server "$SERVER_ADDR" --json stats --fleet "$2" |
    sed -n 's/.*"backlogTraces":"\{0,1\}\([0-9]*\).*/\1/p')
  echo "${n:-0}"
}

# fill_scale_fleet BUILD WORK TRACES: the restart and footprint benchmarks'
# fleet. Writes WORK/fill.textproto (the exact index) and
# WORK/restart.textproto (no periodic snapshot: the snapshot a restart
# starts from is the one the previous stop wrote), both with limits for
# TRACES traces in clusters of 10 (also left in LIMITS), and fills fleet
# "scale" on WORK/data with TRACES 256-d traces (4 robots, batches of 200),
# printing the load generator's summary. FILLED is the traces acknowledged
# (whole batches: a little more than TRACES). HNSW_CODES (int8 or float)
# and HNSW_FLOATS (file or memory), when set, are restart.textproto's
# hnsw { codes floats }.
fill_scale_fleet() {
  local build=$1 work=$2 traces=$3 hnsw=""
  LIMITS="memory { max_clusters: $((traces / 10 + 100)) }
limits { max_traces_per_fleet: $((traces * 2)) }"
  [ -z "${HNSW_CODES:-}" ] || hnsw="codes: \"$HNSW_CODES\""
  [ -z "${HNSW_FLOATS:-}" ] || hnsw="$hnsw floats: \"$HNSW_FLOATS\""
  if [ -n "$hnsw" ]; then
    LIMITS="$LIMITS
hnsw { $hnsw }"
  fi
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

# bench_work NAME [PATH...]: sets WORK for a benchmark: KEEP when set (made
# if needed, kept at exit but for the PATHs in it), else a new temporary
# directory named after NAME (removed at exit). At exit the script's
# background jobs are stopped first.
bench_work() {
  local name=$1 removed="" path
  shift
  if [ -n "${KEEP:-}" ]; then
    WORK=$KEEP
    mkdir -p "$WORK"
    for path in "$@"; do removed="$removed '$WORK/$path'"; done
  else
    WORK=$(mktemp -d "${TMPDIR:-/tmp}/$name.XXXXXX")
    removed="'$WORK'"
  fi
  # shellcheck disable=SC2064  # the paths are fixed now
  trap "kill \$(jobs -p) 2>/dev/null || true; wait; rm -rf $removed" EXIT
}

# fill_scale_fleet_once BUILD WORK TRACES: fill_scale_fleet, then its HNSW
# graph built and saved by a clean stop, unless WORK/filled says an earlier
# run did (a kept WORK: the restart benchmarks' KEEP); FILLED is then read
# back from it.
fill_scale_fleet_once() {
  local build=$1 work=$2 traces=$3
  if [ -f "$work/filled" ]; then
    FILLED=$(cat "$work/filled")
    return
  fi
  rm -rf "$work/data"
  fill_scale_fleet "$build" "$work" "$traces"
  # The first start applies what the fill left waiting and reads every
  # code (the fill's exact index is of another kind): minutes at millions.
  SERVER_START_SECONDS=${SERVER_START_SECONDS:-1200} \
    start_server "$build" "$work/data" "$work/build.log" \
    --config "$work/restart.textproto"
  while [ "$(unindexed_codes "$build" scale)" -gt 0 ]; do sleep 2; done
  stop_server
  echo "$FILLED" >"$work/filled"
}

# serve_fill_copy BUILD WORK NAME LOG [ARGS...]: WORK/data (the fill of
# fill_scale_fleet_once) copied to WORK/NAME, BUILD's server started on the
# copy (WORK/restart.textproto, HTTP on a free port, ARGS), its output in
# LOG, and waited for until its graph holds every code of fleet "scale".
serve_fill_copy() {
  local build=$1 work=$2 name=$3 log=$4
  shift 4
  rm -rf "${work:?}/$name"
  cp -a "$work/data" "$work/$name"
  SERVER_START_SECONDS=1200 start_server "$build" "$work/$name" "$log" \
    --config "$work/restart.textproto" --http-listen 127.0.0.1:0 "$@"
  while [ "$(unindexed_codes "$build" scale)" -gt 0 ]; do sleep 1; done
}

# consolidation_metric: the sum and count of the server's
# fleetmem_consolidation_duration_seconds (SERVER_HTTP_ADDR's /metrics).
consolidation_metric() {
  curl -s "http://$SERVER_HTTP_ADDR/metrics" |
    awk '/^fleetmem_consolidation_duration_seconds_(sum|count)/ { v[$1 ~ /_sum/] += $2 }
         END { printf "%s %s\n", v[1], v[0] }'
}

# perf_report DATA [PERF REPORT ARGS...]: `perf report` of DATA (no call
# graphs, no children), one line per entry, the first TOP (40).
perf_report() {
  local data=$1
  shift
  perf report -i "$data" --no-children --stdio -g none "$@" 2>/dev/null |
    grep -v '^#' | grep '%' | sed 's/  */ /g' |
    head -"${TOP:-40}" || true  # head closes the pipe early: not a failure
}

# server_rss_mib PID: the resident set of fleetmem-server PID, or of the
# fleetmem-server child of PID (a wrapper's), in MiB.
server_rss_mib() {
  local pid
  pid=$(pgrep -P "$1" -f fleetmem-server || echo "$1")
  echo $(( $(ps -o rss= -p "$pid") / 1024 ))
}

# server_held_mib PID: the disk blocks of the files fleetmem-server PID (or
# its child) holds open that no directory shows, in MiB, as "FLOATS HELD":
# its graphs' floats' files (unlinked when made) and snapshot files replaced
# since it opened them (a graph reads its floats from its snapshot's file).
server_held_mib() {
  local pid fd target floats=0 held=0
  pid=$(pgrep -P "$1" -f fleetmem-server || echo "$1")
  for fd in /proc/"$pid"/fd/*; do
    target=$(readlink "$fd" || true)
    case "$target" in
      *graph-floats*) floats=$((floats + $(stat -Lc '%b * %B' "$fd"))) ;;
      *.snapshot*"(deleted)") held=$((held + $(stat -Lc '%b * %B' "$fd"))) ;;
    esac
  done
  echo "$((floats / 1048576)) $((held / 1048576))"
}
