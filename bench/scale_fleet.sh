#!/bin/bash
# One fleet of N 256-d traces on this machine (issue 49: 10,000,000 in 24
# GiB), filled by a bulk import and measured where the goals are set:
#
#   import    `fleetmem import` of a recorded fleet (import_bench's codes:
#             a 16-d gaussian latent through a fixed random map, noise
#             0.05, normalised; place x = row, reward 1), the place graph
#             built once at the end: traces/s, and the graph's seconds;
#   held      RSS; disk: the store (without its index snapshots), the
#             graph's floats file, the index snapshot (after the stop);
#   query     200 codes of the same distribution (rows not imported), k = 10
#             through the Python client, one at a time: p50/p99 as the
#             client sees them and recall@10 against their exact 10 nearest
#             rows (numpy, before the server starts);
#   calls     `fleetmem-load bench --robots 0` for 10 s: QueryPlace (random
#             codes) p50/p99, SampleReplay of 1,000 p50/p99, GetStats p50/p99;
#   consolidation + forgetting
#             a new robot uploads 20,000 traces in segments of 200 into the
#             full memory (K_max lowered to the clusters held after the
#             import: every consolidation forgets):
#             the mean of fleetmem_consolidation_duration_seconds over them
#             (the durable write included);
#   restart   SIGTERM (the index snapshot written; its seconds from the
#             log), then a start timed until the port answers, the engine's
#             load split, the RSS 3 s after and its peak (VmHWM), the disk
#             its graph then holds beside the data dir (floats' file,
#             replaced snapshots still read), and the engine's lines about
#             the load (as comments).
#
#   bench/scale_fleet.sh [BUILD_DIR] [N] [OUT]
#   (default: build 10000000 /dev/stdout; OUT gets one `name,value` per line)
# The run needs about 12 bytes of free disk per float of the payload
# (arrays, store, snapshot, floats file) and, at 10,000,000, hours.
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
n=${2:-10000000}
out=${3:-/dev/stdout}
work=$(mktemp -d "${TMPDIR:-/tmp}/scale-fleet.XXXXXX")
trap 'kill $(jobs -p) 2>/dev/null || true; wait; rm -rf "$work"' EXIT
python=$("$here/clients/python/install_venv.sh" "$build/python-venv")
source "$here/tools/load/server_lib.sh"
: >"$work/rows.csv"
row() { echo "$1,$2" | tee -a "$work/rows.csv" >&2; }
seconds_since() { awk "BEGIN { printf \"%.2f\", $(date +%s.%N) - $1 }"; }

# The recorded fleet, its queries and their exact neighbours, a million
# rows at a time.
mkdir -p "$work/arrays"
/usr/bin/python3 - "$work" "$n" <<'PY'
import sys, numpy as np
work, n = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(7)
basis = rng.standard_normal((16, 256))
def codes_of(rows):
    c = rng.standard_normal((rows, 16)) @ basis
    c += 0.05 * np.sqrt((c ** 2).mean()) * rng.standard_normal((rows, 256))
    return (c / np.linalg.norm(c, axis=1, keepdims=True)).astype("<f4")
queries = codes_of(200)
np.save(f"{work}/queries.npy", queries)
codes = np.lib.format.open_memmap(f"{work}/arrays/codes.npy", mode="w+",
                                  dtype="<f4", shape=(n, 256))
best_d = np.full((200, 10), np.inf)
best_i = np.zeros((200, 10), np.int64)
step = 1_000_000
for first in range(0, n, step):
    rows = min(step, n - first)
    block = codes_of(rows)
    codes[first:first + rows] = block
    d = (queries ** 2).sum(1)[:, None] - 2 * queries @ block.T + (block ** 2).sum(1)[None, :]
    k = min(10, rows)
    near = np.argpartition(d, k - 1, axis=1)[:, :k]
    all_d = np.concatenate([best_d, np.take_along_axis(d, near, 1)], 1)
    all_i = np.concatenate([best_i, near + first], 1)
    keep = np.argsort(all_d, axis=1)[:, :10]
    best_d = np.take_along_axis(all_d, keep, 1)
    best_i = np.take_along_axis(all_i, keep, 1)
codes.flush()
del codes
np.save(f"{work}/truth.npy", best_i)
places = np.lib.format.open_memmap(f"{work}/arrays/places.npy", mode="w+",
                                   dtype="<f8", shape=(n, 4))
for first in range(0, n, step):
    rows = min(step, n - first)
    places[first:first + rows] = 0
    places[first:first + rows, 0] = np.arange(first, first + rows)
places.flush()
del places
np.save(f"{work}/arrays/rewards.npy", np.ones(n))
PY
payload_mib=$((n * 256 * 4 / 1048576))
row traces "$n"
row payload_mib "$payload_mib"

# No periodic index snapshot: one would hold the fleet's writes (23 s at
# 10,000,000) in the middle of a timed phase; the stop writes it.
printf 'index_snapshot_interval_seconds: 0\nmemory { max_clusters: %d }\nlimits { max_traces_per_fleet: %d }\n' \
  $((n / 10 + 100)) $((n * 2)) >"$work/server.textproto"
SERVER_START_SECONDS=3600 start_server "$build" "$work/data" \
  "$work/server.log" --config "$work/server.textproto" \
  --http-listen 127.0.0.1:0
fm() { "$build/bin/fleetmem" --server "$SERVER_ADDR" "$@"; }
# fleet_stat FIELD: the fleet's GetStats FIELD (protobuf JSON's name; 0 if left out).
fleet_stat() {
  fm --json stats --fleet big | /usr/bin/python3 -c \
    'import json, sys; print(int(json.load(sys.stdin).get(sys.argv[1], 0)))' "$1"
}

start=$(date +%s.%N)
# The load generator's encoder, for its uploads below.
fm import --fleet big --from "$work/arrays" --robot import --encoder load-v1 \
  >"$work/import.out"
import_s=$(seconds_since "$start")
row import_seconds "$import_s"
row import_traces_per_s "$(awk -v n="$n" -v s="$import_s" 'BEGIN { printf "%.0f", n / s }')"
row import_graph_seconds "$(sed -n 's/.*graph built in \([0-9.]*\) s.*/\1/p' "$work/import.out")"
row held_traces "$(fleet_stat traces)"
row unindexed_codes "$(unindexed_codes "$build" big)"

mib() { echo $(( $(du -sk "$@" | awk '{ s += $1 } END { print s }') / 1024 )); }
rss=$(server_rss_mib "$SERVER_PID")
row rss_mib "$rss"
row rss_over_payload "$(awk -v r="$rss" -v p="$payload_mib" 'BEGIN { printf "%.2f", r / p }')"
row store_mib "$(mib --exclude=index-snapshots "$work/data/db")"
# The floats' file is unlinked when made: its blocks, through the server's
# descriptor; and a snapshot file replaced but still read.
held=$(server_held_mib "$SERVER_PID")
row floats_file_mib "${held% *}"
row held_snapshot_mib "${held#* }"

"$python" - "$SERVER_ADDR" "$work" <<'PY' >>"$work/rows.csv"
import sys, time, numpy as np, fleetmem
server, work = sys.argv[1], sys.argv[2]
queries = np.load(f"{work}/queries.npy")
truth = np.load(f"{work}/truth.npy")
ms, hits = [], 0
with fleetmem.Client(server) as fm:
    for q, want in zip(queries, truth):
        start = time.perf_counter()
        matches = fm.query_place("big", q, k=10)
        ms.append((time.perf_counter() - start) * 1000)
        got = set(int(x) for x in matches.traces.places[:, 0])
        hits += len(got & set(int(x) for x in want))
ms.sort()
print(f"query_client_p50_ms,{ms[len(ms) // 2]:.2f}")
print(f"query_client_p99_ms,{ms[int(0.99 * (len(ms) - 1))]:.2f}")
print(f"query_recall_at_10,{hits / truth.size:.4f}")
PY
tail -3 "$work/rows.csv" >&2

"$build/bin/fleetmem-load" bench --server "$SERVER_ADDR" --fleet big \
  --dimension 256 --robots 0 --seconds 10 --query-rate 20 --sample-rate 5 \
  --stats-rate 10 --csv "$work/calls.csv" >/dev/null 2>&1
calls=$(sed -n 2p "$work/calls.csv")
col() { echo "$calls" | cut -d, -f"$1"; }
row query_p50_ms "$(col 13)"
row query_p99_ms "$(col 14)"
row sample_1000_p50_ms "$(col 16)"
row sample_1000_p99_ms "$(col 17)"
row stats_p50_ms "$(col 19)"
row stats_p99_ms "$(col 20)"

# consolidation_metric: the histogram's sum and count, all fleets.
consolidation_metric() {
  curl -s "http://$SERVER_HTTP_ADDR/metrics" |
    awk '/^fleetmem_consolidation_duration_seconds_(sum|count)/ { v[$1 ~ /_sum/] += $2 }
         END { printf "%s %s\n", v[1], v[0] }'
}
# The memory made full: K_max lowered to the clusters held, so that every
# consolidation below forgets.
held_clusters=$(fleet_stat clusters)
row held_clusters "$held_clusters"
fm update-fleet --fleet big --max-clusters "$held_clusters" >/dev/null
forgotten0=$(fleet_stat clustersForgotten)
read -r sum0 count0 < <(consolidation_metric)
"$build/bin/fleetmem-load" upload --server "$SERVER_ADDR" --fleet big \
  --dimension 256 --robots 1 --batch 200 --seconds 100000 --traces 20000 \
  >/dev/null
while [ "$(backlog_traces "$build" big)" -gt 0 ]; do sleep 1; done
read -r sum1 count1 < <(consolidation_metric)
row consolidations "$(awk -v a="$count0" -v b="$count1" 'BEGIN { print b - a }')"
row consolidation_mean_ms "$(awk -v s0="$sum0" -v s1="$sum1" -v a="$count0" -v b="$count1" \
  'BEGIN { printf "%.2f", (b > a ? 1000 * (s1 - s0) / (b - a) : 0) }')"
row clusters_forgotten_during_uploads "$(($(fleet_stat clustersForgotten) - forgotten0))"

stop_server
row snapshot_seconds "$(sed -n 's/.*index snapshot of [0-9]* codes saved in \([0-9.]*\) s.*/\1/p' "$work/server.log" | tail -1)"
row snapshot_mib "$(mib "$work/data/db/index-snapshots")"
row disk_mib "$(mib "$work/data")"
start=$(date +%s.%N)
SERVER_START_SECONDS=3600 start_server "$build" "$work/data" \
  "$work/restart.log" --config "$work/server.textproto"
row restart_port_seconds "$(seconds_since "$start")"
sleep 3
row restart_rss_mib "$(server_rss_mib "$SERVER_PID")"
# What the graph holds beside the data dir after the start: since the
# tenth round it reads its floats from the snapshot's file (no copy).
held=$(server_held_mib "$SERVER_PID")
row restart_floats_file_mib "${held% *}"
row restart_held_snapshot_mib "${held#* }"
split=$(sed -n 's/.*store read \([0-9.]*\) s, memory and index \([0-9.]*\) s.*/\1 \2/p' \
  "$work/restart.log")
row restart_store_read_seconds "${split% *}"
row restart_memory_and_index_seconds "${split#* }"
# The load's peak resident set, and the engine's own lines about it (the
# store's split or the memory image's, the wait for the snapshot's
# handles, the reconcile).
server_pid=$(pgrep -P "$SERVER_PID" -f fleetmem-server || echo "$SERVER_PID")
row restart_peak_rss_mib "$(awk '/^VmHWM/ { printf "%d", $2 / 1024 }' "/proc/$server_pid/status")"
grep -o 'fleet "big"\(: read [0-9]* trace records\|: index snapshot reconciled\|: [0-9]* traces in [0-9]* clusters taken\| loaded:\).*' \
  "$work/restart.log" | sed 's/^/# /' >>"$work/rows.csv"
stop_server
[ "$out" = /dev/stdout ] || cp "$work/rows.csv" "$out"
cat "$work/rows.csv"
