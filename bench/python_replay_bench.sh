#!/usr/bin/env bash
# Replay into a Python training loop (issue 48's goal: ReplayDataset feeds
# >= 50,000 traces/s of 256-d codes), against calling sample_replay in a
# loop, in one run on one server and one fleet. A fleet of N D-dimensional
# codes (bounds large enough that every trace is kept) is uploaded, then
# each way draws TRACES traces in batches of BATCH into a loop that touches
# every batch's codes (their mean), REPS times, alternating which goes
# first:
#   messages   sample_replay(columnar=False) in a loop (the answer as one
#              message per trace: the client's path before this change)
#   columns    sample_replay() in a loop (the answer as columns)
#   dataset    ReplayDataset (columns, 2 batches prefetched on a thread)
#   bench/python_replay_bench.sh [BUILD] [OUT_CSV]
# Environment: N (20000), D (256), TRACES (100000), BATCH (1000), REPS (3).
set -euo pipefail
root=$(cd "$(dirname "$0")/.." && pwd)
build=${1:-$root/build}
out=${2:-/dev/stdout}
n=${N:-20000} dim=${D:-256} traces=${TRACES:-100000} batch=${BATCH:-1000} reps=${REPS:-3}
work=$(mktemp -d)
trap 'kill "$SERVER_PID" 2>/dev/null || true; rm -rf "$work"' EXIT
python=$("$root/clients/python/install_venv.sh" "$build/python-venv")
# shellcheck source=../tools/process/server.sh
source "$root/tools/process/server.sh"
printf 'memory { max_clusters: 100000 max_traces_per_cluster: 100000 }\n' \
  > "$work/server.textproto"
start_server "$build" "$work/data" "$work/server.log" --config "$work/server.textproto"
"$python" - "$SERVER_ADDR" "$n" "$dim" "$traces" "$batch" "$reps" > "$work/rows.csv" <<'PY'
import sys, time
import numpy as np
import fleetmem
server, n, dim, traces, batch, reps = sys.argv[1], *map(int, sys.argv[2:])
rng = np.random.default_rng(48)
codes = rng.standard_normal((n, dim)).astype(np.float32)
with fleetmem.Client(server, batch_size=1000) as fm:
    fm.upload("replay", codes, np.arange(n, dtype=np.float64), rng.uniform(0.1, 1, n).astype(np.float32),
              robot_id="r1", seqs=np.arange(n))
    fm.consolidate("replay")
    held = fm.stats("replay").traces
    assert held == n, (held, n)

    def loop(batches):
        start, drawn, checksum = time.monotonic(), 0, 0.0
        for b in batches:
            assert b.codes.shape[1] == dim
            checksum += float(b.codes.mean())   # the loop touches every code
            drawn += len(b)
        return drawn, time.monotonic() - start

    ways = {
        "messages": lambda: (fm.sample_replay("replay", "r1", batch, columnar=False)
                             for _ in range(traces // batch)),
        "columns": lambda: (fm.sample_replay("replay", "r1", batch) for _ in range(traces // batch)),
        "dataset": lambda: fleetmem.ReplayDataset(fm, "replay", "r1", batch_size=batch,
                                                  batches=traces // batch),
    }
    print("rep,way,traces,dim,batch,seconds,traces_per_s")
    for rep in range(1, reps + 1):
        order = list(ways) if rep % 2 else list(reversed(ways))
        for way in order:
            drawn, seconds = loop(ways[way]())
            print(f"{rep},{way},{drawn},{dim},{batch},{seconds:.3f},{drawn / seconds:.0f}", flush=True)
PY
cat "$work/rows.csv" >&2
"$python" - "$work/rows.csv" > "$out" <<'PY'
import csv, statistics, sys
rows = list(csv.DictReader(open(sys.argv[1])))
rate = {}
for row in rows:
    rate.setdefault(row["way"], []).append(float(row["traces_per_s"]))
base = statistics.median(rate["messages"])
print("way,median_traces_per_s,min,max,ratio_to_messages")
for way, values in rate.items():
    print(f"{way},{statistics.median(values):.0f},{min(values):.0f},{max(values):.0f},"
          f"{statistics.median(values) / base:.2f}")
PY
