#!/usr/bin/env bash
# Upload throughput of the Python client against the C++ client's, on one
# server and the same codes, alternating which goes first (issue 31's goal:
# Python >= 50 % of C++). Each run uploads N codes of dimension D from one
# robot into a fresh fleet, durable acks (the client's cost is what is
# measured; applied acks would measure the server's consolidation), and
# REPS runs of each.
#   bench/python_upload_bench.sh [BUILD] [OUT_CSV]
# Environment: N (100000), D (256), REPS (3), BATCH (500).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
out=${2:-/dev/stdout}
n=${N:-100000} dim=${D:-256} reps=${REPS:-3} batch=${BATCH:-500}
work=$(mktemp -d)
trap 'kill "$SERVER_PID" 2>/dev/null || true; rm -rf "$work"' EXIT
python=$("$root/clients/python/install_venv.sh" "$build/python-venv")
# shellcheck source=../tools/process/server.sh
source "$root/tools/process/server.sh"
start_server "$build" "$work/data" "$work/server.log"
"$python" - "$work/codes.f32" "$n" "$dim" <<'PY'
import sys, numpy as np
path, n, d = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
np.random.default_rng(31).standard_normal((n, d)).astype("<f4").tofile(path)
PY
echo "rep,client,traces,dim,batch,seconds,traces_per_s" >"$work/rows.csv"
for rep in $(seq 1 "$reps"); do
  order="cpp python"
  [ $((rep % 2)) = 0 ] && order="python cpp"
  for client in $order; do
    fleet="bench-$client-$rep"
    if [ "$client" = cpp ]; then
      line=$("$build/bin/fleetmem_client_upload_bench" --server "$SERVER_ADDR" \
        --codes "$work/codes.f32" --dim "$dim" --fleet "$fleet" --robot r1 \
        --batch "$batch")
    else
      line=$("$python" - "$SERVER_ADDR" "$work/codes.f32" "$dim" "$fleet" "$batch" <<'PY'
import json, sys, time
import numpy as np
import fleetmem
server, path, dim, fleet, batch = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], int(sys.argv[5])
codes = np.fromfile(path, "<f4").reshape(-1, dim)
n = len(codes)
with fleetmem.Client(server, batch_size=batch) as fm:
    start = time.monotonic()
    # What a Python robot has: its codes and places as arrays.
    result = fm.upload(fleet, codes, np.arange(n, dtype=np.float64), 1.0, robot_id="r1",
                       seqs=np.arange(n), ack="durable")
    seconds = time.monotonic() - start
print(json.dumps({"client": "python", "traces": n, "accepted": result.accepted,
                  "seconds": seconds, "traces_per_s": n / seconds}))
PY
)
    fi
    echo "$line" >&2
    "$python" - "$rep" "$dim" "$batch" "$line" >>"$work/rows.csv" <<'PY'
import json, sys
rep, dim, batch, row = sys.argv[1], sys.argv[2], sys.argv[3], json.loads(sys.argv[4])
assert row["accepted"] == row["traces"], row
print(f'{rep},{row["client"]},{row["traces"]},{dim},{batch},{row["seconds"]:.3f},{row["traces_per_s"]:.0f}')
PY
  done
done
"$python" - "$work/rows.csv" <<'PY' >&2
import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
for rep in sorted({r["rep"] for r in rows}):
    by = {r["client"]: float(r["traces_per_s"]) for r in rows if r["rep"] == rep}
    print(f"run {rep}: python {by['python']:.0f}/s, C++ {by['cpp']:.0f}/s, ratio {by['python'] / by['cpp']:.2f}")
PY
cp "$work/rows.csv" "$out" 2>/dev/null || cat "$work/rows.csv"
stop_server
