#!/bin/bash
# Bulk import against uploads of the same codes, on one server in one run
# (issue 49's goal: an import at >= 5x the applied rate of uploads).
#
# A recorded fleet of N 256-d codes (synthetic, as docs/performance.md's:
# a 16-d gaussian latent through a fixed random map, noise 0.05,
# normalised), its places (x = row) and rewards (1), as the upload client
# below makes them, written as .npy arrays (codes.npy, places.npy,
# rewards.npy: `fleetmem import`'s input without metadata).
# The server keeps every trace (K_max = N/10 + 100, no downsampling).
#   upload  fleetmem_client_upload_bench, one stream, batches of 200,
#           durable acknowledgements: from the first byte until every trace
#           is applied and in the place graph (GetStats: no backlog, no
#           unindexed code);
#   import  fleetmem import --from DIR: from the start until its last call
#           answers (every row applied, the graph built); the graph's
#           build alone is the last call's index_seconds;
#   hnswlib Debian's python3-hnswlib inserting the same codes into its own
#           graph (float L2, M = 16, ef_construction = 40, as the server's
#           default graph, 2 threads), with the server idle: the graph's
#           peer.
# Each into its own fleet; the order alternates over REPS rounds.
#
#   bench/import_bench.sh [BUILD_DIR] [OUT_CSV] [N]
# Environment: REPS (1); HNSW_CODES (int8 or float: the server's graph
# codes, hnsw { codes }; unset: the server's default), its column `codes`;
# INDEXER_BATCH (hnsw { indexer_batch }; unset: the server's default).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$here/build}
out=${2:-/dev/stdout}
n=${3:-100000}
reps=${REPS:-1}
work=$(mktemp -d "${TMPDIR:-/tmp}/import-bench.XXXXXX")
trap 'kill $(jobs -p) 2>/dev/null || true; rm -rf "$work"' EXIT
source "$here/tools/load/server_lib.sh"
mkdir -p "$work/arrays"
/usr/bin/python3 - "$work/arrays" "$n" <<'PY'
import sys, numpy as np
out, n = sys.argv[1], int(sys.argv[2])
rng = np.random.default_rng(7)
basis = rng.standard_normal((16, 256))
codes = rng.standard_normal((n, 16)) @ basis
codes += 0.05 * np.sqrt((codes ** 2).mean()) * rng.standard_normal((n, 256))
codes /= np.linalg.norm(codes, axis=1, keepdims=True)
codes = codes.astype("<f4")
np.save(f"{out}/codes.npy", codes)
codes.tofile(f"{out}/../codes.f32")
# As fleetmem_client_upload_bench makes them: place x = row, reward 1.
places = np.zeros((n, 4))
places[:, 0] = np.arange(n)
np.save(f"{out}/places.npy", places)
np.save(f"{out}/rewards.npy", np.ones(n))
PY
printf 'memory { max_clusters: %d }\nlimits { max_traces_per_fleet: %d }\n' \
  $((n / 10 + 100)) $((n * 2)) >"$work/server.textproto"
codes=${HNSW_CODES:-default}
hnsw=""
[ -z "${HNSW_CODES:-}" ] || hnsw="codes: \"$HNSW_CODES\""
if [ -n "${INDEXER_BATCH:-}" ]; then
  hnsw="$hnsw indexer_batch: $INDEXER_BATCH"
  codes="$codes/batch-$INDEXER_BATCH"
fi
[ -z "$hnsw" ] || printf 'hnsw { %s }\n' "$hnsw" >>"$work/server.textproto"
start_server "$build" "$work/data" "$work/server.log" \
  --config "$work/server.textproto"

now() { date +%s.%N; }
# held FLEET: traces + pending, backlog traces and unindexed codes.
held() {
  "$build/bin/fleetmem" --server "$SERVER_ADDR" --json stats --fleet "$1" |
    python3 -c 'import json,sys; s=json.load(sys.stdin)
print(int(s.get("traces",0))+int(s.get("pendingTraces",0)),
      int(s.get("backlogTraces",0)), int(s.get("unindexedCodes",0)))'
}
run_upload() {
  local fleet=$1 start
  start=$(now)
  "$build/bin/fleetmem_client_upload_bench" --server "$SERVER_ADDR" \
    --codes "$work/codes.f32" --dim 256 --fleet "$fleet" --robot import \
    --batch 200 >/dev/null
  local acked
  acked=$(now)
  while true; do
    read -r traces backlog unindexed < <(held "$fleet")
    [ "$traces" -ge "$n" ] && [ "$backlog" = 0 ] && [ "$unindexed" = 0 ] &&
      break
    sleep 0.2
  done
  python3 -c "import sys; a,b,c=map(float,sys.argv[1:]); print(f'{b-a:.2f} {c-a:.2f}')" \
    "$start" "$acked" "$(now)"
}
run_import() {
  local fleet=$1 start
  start=$(now)
  "$build/bin/fleetmem" --server "$SERVER_ADDR" import --fleet "$fleet" \
    --from "$work/arrays" --robot import >"$work/import.out" 2>/dev/null
  local done_at
  done_at=$(now)
  sed 's/^/# /' "$work/import.out" >&2
  INDEX_SECONDS=$(sed -n 's/.*graph built in \([0-9.]*\) s.*/\1/p' \
    "$work/import.out")
  read -r traces backlog unindexed < <(held "$fleet")
  [ "$traces" -ge "$n" ] && [ "$backlog" = 0 ] && [ "$unindexed" = 0 ] || {
    echo "import into $fleet left $traces traces, $backlog backlog," \
      "$unindexed unindexed" >&2
    exit 1
  }
  python3 -c "import sys; a,b=map(float,sys.argv[1:]); print(f'{b-a:.2f}')" \
    "$start" "$done_at"
}
hnswlib_seconds() {
  /usr/bin/python3 - "$work/arrays/codes.npy" <<'PY'
import sys, time, numpy as np, hnswlib
codes = np.load(sys.argv[1])
index = hnswlib.Index(space="l2", dim=codes.shape[1])
index.init_index(max_elements=len(codes), M=16, ef_construction=40,
                 random_seed=42)
index.set_num_threads(2)
start = time.perf_counter()
index.add_items(codes, np.arange(len(codes)))
print(f"{time.perf_counter() - start:.2f}")
PY
}
echo "codes,round,traces,upload_acked_s,upload_applied_s,upload_applied_per_s,import_s,import_per_s,ratio,import_index_s,hnswlib_s,graph_to_hnswlib" >"$work/rows.csv"
for round in $(seq 1 "$reps"); do
  order="upload import"
  [ $((round % 2)) = 0 ] && order="import upload"
  for what in $order; do
    if [ "$what" = upload ]; then
      read -r acked applied < <(run_upload "up-$round")
    else
      run_import "imp-$round" >"$work/import.s"
      imported=$(cat "$work/import.s")
    fi
  done
  # The graph's peer, with the server idle.
  hnsw=$(hnswlib_seconds)
  python3 -c "import sys; n,a,b,c,i,h=int(sys.argv[1]),*map(float,sys.argv[2:7])
print(f'{sys.argv[8]},{sys.argv[7]},{n},{a:.2f},{b:.2f},{n/b:.0f},{c:.2f},{n/c:.0f},{b/c:.2f},{i:.2f},{h:.2f},{h/i:.2f}')" \
    "$n" "$acked" "$applied" "$imported" "$INDEX_SECONDS" "$hnsw" "$round" \
    "$codes" >>"$work/rows.csv"
done
stop_server
cat "$work/rows.csv" >"$out"
[ "$out" = /dev/stdout ] || cat "$work/rows.csv"
