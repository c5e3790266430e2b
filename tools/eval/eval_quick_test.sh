#!/usr/bin/env bash
# End-to-end check of `fleetmem-eval lifelong --quick` on the real data:
# every method runs (the memory methods through real fleetmem-server
# children) and writes the files the protocol promises.
# Usage: eval_quick_test.sh BIN_DIR DATA_ROOT OUT_DIR
set -euo pipefail
bin_dir="$1" data_root="$2" out="$3"
rm -rf "$out"
"$bin_dir/fleetmem-eval" lifelong --data-root "$data_root" --out "$out" --quick
fail() { echo "eval_quick_test: $*" >&2; exit 1; }
[[ "$(head -1 "$out/summary.csv")" == "method,wr_final,ae,ra" ]] || fail "summary.csv header"
methods="classical gpl_pretrained finetune uniform_replay bioslam no_rex no_rin no_clustering no_decay bioslam_decoded fleet_shared"
for m in $methods; do
  row="$(grep "^$m," "$out/summary.csv")" || fail "no row for $m in summary.csv"
  IFS=, read -r _ wr ae ra <<<"$row"
  for v in "$wr" "$ae" "$ra"; do
    awk -v v="$v" 'BEGIN { exit !(v >= 0 && v <= 1) }' || fail "$m: value $v outside [0, 1]"
  done
done
[[ "$(wc -l <"$out/summary.csv")" -eq 12 ]] || fail "summary.csv should have 11 rows"
# curves.csv: 6 x 6 rows for each method that learns over domains (all but fleet_shared).
[[ "$(grep -c '^bioslam,' "$out/curves.csv")" -eq 36 ]] || fail "curves.csv lacks bioslam's 36 rows"
[[ "$(head -c 4 "$out/curves.png" | od -An -tx1 | tr -d ' ')" == "89504e47" ]] || fail "curves.png is not a PNG"
[[ "$(wc -l <"$out/fleet.csv")" -eq 3 ]] || fail "fleet.csv should have 2 robot rows"
[[ -s "$out/encoder.pt" ]] || fail "no encoder.pt"
echo "eval_quick_test: all outputs present and well-formed"
