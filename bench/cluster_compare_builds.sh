#!/usr/bin/env bash
# Distributed mode's ingest of two server builds, measured alternately in
# one run (this VM's rates drift between minutes): ROUNDS rounds of
# bench/cluster_scaling.sh with 1 and 3 replicas (REPLICAS to change it),
# against A's build, then B's. Keeps every round's table in OUT_DIR and
# prints, per replica count, the mean acknowledged and applied rates of
# each build and B / A.
#
#   bench/cluster_compare_builds.sh A_BUILD_DIR B_BUILD_DIR ROUNDS OUT_DIR
#
# A build directory holds bin/fleetmem-server, bin/fleetmem-load and
# bin/fleetmem (cluster_scaling.sh runs all three from it).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
if [ $# -lt 4 ]; then
  sed -n '2,12p' "$0" >&2
  exit 2
fi
a=$1 b=$2 rounds=$3 out=$4
for dir in "$a" "$b"; do
  for tool in fleetmem-server fleetmem-load fleetmem; do
    if [ ! -x "$dir/bin/$tool" ]; then
      echo "$dir/bin/$tool: no such executable" >&2
      exit 2
    fi
  done
done
mkdir -p "$out"
export REPLICAS=${REPLICAS:-"1 3"}
for round in $(seq 1 "$rounds"); do
  for side in a b; do
    dir=$a
    [ "$side" = b ] && dir=$b
    "$here/bench/cluster_scaling.sh" "$dir" "$out/$side-$round.txt" \
      >"$out/$side-$round.log" 2>&1
    echo "round $round, $side: $(grep -E '^[0-9]+ ' "$out/$side-$round.txt" |
      awk '{printf "%s replicas %s/s acknowledged, %s/s applied; ", $1, $2, $4}')"
  done
done
python3 - "$out" "$rounds" <<'EOF'
import collections, statistics, sys
out, rounds = sys.argv[1], int(sys.argv[2])
rates = collections.defaultdict(list)  # (side, replicas, what) -> values
for side in "ab":
    for r in range(1, rounds + 1):
        for line in open(f"{out}/{side}-{r}.txt"):
            f = line.split()
            if f and f[0].isdigit():
                rates[(side, f[0], "ingest")].append(float(f[1]))
                rates[(side, f[0], "applied")].append(float(f[3]))
print(f"{'replicas':>8} {'what':>8} {'A mean':>9} {'B mean':>9} {'B / A':>6}"
      "  (each build's rounds)")
for replicas in sorted({k[1] for k in rates}, key=int):
    for what in ("ingest", "applied"):
        av, bv = rates[("a", replicas, what)], rates[("b", replicas, what)]
        ma, mb = statistics.mean(av), statistics.mean(bv)
        print(f"{replicas:>8} {what:>8} {ma:9.0f} {mb:9.0f} {mb / ma:6.2f}  "
              f"A {' '.join(f'{v:.0f}' for v in av)}; "
              f"B {' '.join(f'{v:.0f}' for v in bv)}")
EOF
