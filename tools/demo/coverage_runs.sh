#!/usr/bin/env bash
# docs/results.md, "Memory coverage under the bound": the demo's fleet at
# 900, 1,800 and 2,500 traces (3 robots x 300, 600, 833 frames, K_max = 100)
# and at 1,800 traces with K_max = 20, each with forgetting by merging (the
# server's default) and by dropping (merge_on_forget: false, the paper's
# Algorithm 2); no learning pass. Prints one line per run: traces held,
# query places covered, the memory's and the unbounded baseline's
# recall@1 / WR. The robots drive one after another, so a run repeats
# exactly (side by side, the drop runs vary by about a point). A few minutes.
#
#   tools/demo/coverage_runs.sh [BUILD_DIR] [WORK_DIR]
set -euo pipefail
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
build=${1:-build}
work=${2:-$(mktemp -d)}
mkdir -p "$work"
printf '| traces | K_max | forgetting | held | covered | r@1 | WR | unbounded r@1 / WR |\n'
printf '|---|---:|---|---:|---|---:|---:|---|\n'
for run in "300 100" "600 100" "833 100" "600 20"; do
  read -r length kmax <<<"$run"
  for mode in merge drop; do
    config="$work/k$kmax-$mode.textproto"
    printf 'memory { max_clusters: %d merge_on_forget: %s }\n' "$kmax" \
      "$([ "$mode" = merge ] && echo true || echo false)" >"$config"
    dir="$work/$mode-$length-k$kmax"
    FLEETMEM_DEMO_DIR="$dir" FLEETMEM_DEMO_SERVER_ARGS="--config $config" \
      "$root/tools/demo/run_demo.sh" "$build" --stretch-length "$length" \
      --fleet "cov-$mode-$length-k$kmax" --learn=false --sequential-robots \
      >"$dir.log" 2>&1 || {
      tail -20 "$dir.log"
      exit 1
    }
    python3 - "$dir/results.md" "$length" "$kmax" "$mode" <<'PY'
import re, sys
text = open(sys.argv[1]).read()
rows = {l.split("|")[1].strip(): [c.strip() for c in l.split("|")[2:-1]]
        for l in text.splitlines() if l.startswith("| fleet memory") or l.startswith("| all traces")}
mem = next(v for k, v in rows.items() if k.startswith("fleet memory"))
base = next(v for k, v in rows.items() if k.startswith("all traces"))
cov = re.search(r"within \+-2 files of (\d+) of (\d+) query places \(([\d.]+)%\)", text)
print("| %d | %s | %s | %s | %s %% (%s of %s) | %s | %s | %s / %s |" % (
    3 * int(sys.argv[2]), sys.argv[3], sys.argv[4], mem[3], cov.group(3),
    cov.group(1), cov.group(2), mem[0], mem[2], base[0], base[2]))
PY
  done
done
