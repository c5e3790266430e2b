#!/usr/bin/env python3
"""`fleetmem-eval lifelong` end to end on the real data: every method runs
(the memory methods through real fleetmem-server children) and writes the
files protocol v2 promises, with numbers that agree with their definitions
as computed here (docs/results.md, tools/eval/lifelong_protocol.h):

  - every curves.csv row (method, seed, after domain t, area a: the winter
    queries of area a's held-out places against the summer map): WR = 0.5 r1
    + 0.1 (r2 + ... + r6), recall@k non-decreasing in k, each recall a
    multiple of 1 / (queries of the area);
  - summary.csv from curves.csv, per seed and then the mean over seeds:
    WR final = the mean WR over the three areas after the last domain, AE =
    the mean over the winter domains of the WR on the area just learned, RA
    = the mean over the later winter domains of the mean WR on the winter
    areas learned before;
  - the chance row from the count of correct map entries per query;
  - the methods that do not learn over the domains (classical,
    classical_seq, joint, joint_seq, gpl_pretrained, gpl_joint,
    gpl_e2e_joint) score the same after every domain;
  - uniform_replay and uniform_seq never hold more traces than bioslam
    (memory.csv).

--quick (ctest fleetmem_eval_quick_test, slow tier): the quick settings on
the whole route. --smoke (ctest fleetmem_eval_smoke_test, `make test`): the
first SMOKE_PLACES places and a few steps, which prove the code paths and
the report's arithmetic, not the learning.

usage: check_lifelong.py BIN_DIR DATA_ROOT OUT_DIR (--quick | --smoke)
"""
import csv
import os
import shutil
import subprocess
import sys

SMOKE_PLACES = 48  # 3 areas of 16 places, every 4th held out: 4 queries each
METHODS = ["classical", "classical_seq", "classical_seq_robot", "joint", "joint_seq", "finetune", "bioslam",
           "bioslam_drop", "bioslam_iw", "bioslam_rescore", "bioslam_seq", "bioslam_seq_robot",
           "bioslam_pairs", "pairs_uniform", "fleet_uniform", "pairs_flat_rewards",
           "uniform_replay", "uniform_seq", "no_rex", "no_rin", "no_clustering", "no_decay",
           "fleet_shared", "fleet_shared_pairs", "fleet_shared_flat", "gpl_pretrained", "gpl_joint", "gpl_e2e_joint",
           "gpl_finetune",
           "gpl_bioslam", "gpl_bioslam_decoded"]
STATIC = ["classical", "classical_seq", "classical_seq_robot", "joint", "joint_seq", "gpl_pretrained", "gpl_joint",
          "gpl_e2e_joint"]
DOMAINS, AREAS, TOLERANCE = 6, 3, 2
TOL = 2e-4  # the files print 4 decimals


def close(a, b):
    return abs(a - b) <= TOL


def main():
    bin_dir, data_root, out = sys.argv[1:4]
    smoke = "--smoke" in sys.argv[4:]
    shutil.rmtree(out, ignore_errors=True)
    command = [os.path.join(bin_dir, "fleetmem-eval"), "lifelong",
               "--data-root", data_root, "--out", out, "--quick"]
    if smoke:
        command += ["--places", str(SMOKE_PLACES), "--threads", "1",
                    "--pretrain-steps", "3", "--end-to-end-steps", "3",
                    "--steps-per-segment", "2"]
    subprocess.run(command, check=True)

    with open(os.path.join(out, "summary.csv")) as f:
        summary = {r["method"]: r for r in csv.DictReader(f)}
    assert list(summary) == ["chance"] + METHODS, list(summary)
    for m, r in summary.items():
        for k in ("wr_final", "ae", "ra"):
            assert 0 <= float(r[k]) <= 1, (m, k, r[k])

    n = SMOKE_PLACES if smoke else None
    if n is not None:  # the chance level, counted here
        queries = [q for q in range(n) if held_out(q, n)]
        recall = []
        for k in range(1, 7):
            found = 0.0
            for q in queries:
                m = min(n - 1, q + TOLERANCE) - max(0, q - TOLERANCE) + 1
                none = 1.0
                for i in range(k):
                    none *= (n - m - i) / (n - i)
                found += 1 - none
            recall.append(found / len(queries))
        chance = 0.5 * recall[0] + 0.1 * sum(recall[1:])
        assert close(float(summary["chance"]["wr_final"]), chance), (
            summary["chance"], chance)

    with open(os.path.join(out, "curves.csv")) as f:
        rows = list(csv.DictReader(f))
    wr = {}  # (method, seed, after, area) -> WR
    for r in rows:
        recall = [float(r[f"r{k}"]) for k in range(1, 7)]
        assert all(a <= b + 1e-9 for a, b in zip(recall, recall[1:])), r
        assert close(float(r["wr"]), 0.5 * recall[0] + 0.1 * sum(recall[1:])), r
        if smoke:
            for x in recall:  # 4 queries per area
                assert close(x * 4, round(x * 4)), r
        wr[(r["method"], int(r["seed"]), int(r["after_domain"]),
            int(r["area"]))] = float(r["wr"])
    for m in METHODS:
        if m.startswith("fleet_shared"):  # reports per robot (fleet.csv)
            continue
        seeds = sorted({k[1] for k in wr if k[0] == m})
        assert seeds, m
        per_seed = {"wr_final": [], "ae": [], "ra": []}
        for seed in seeds:
            cells = [k for k in wr if k[0] == m and k[1] == seed]
            assert len(cells) == DOMAINS * AREAS, (m, seed, len(cells))
            w = lambda t, a: wr[(m, seed, t, a)]
            per_seed["wr_final"].append(
                sum(w(DOMAINS, a) for a in range(1, AREAS + 1)) / AREAS)
            # winter domain t (4..6) learns area t - 3
            per_seed["ae"].append(
                sum(w(t, t - AREAS) for t in range(AREAS + 1, DOMAINS + 1)) / AREAS)
            per_seed["ra"].append(
                sum(sum(w(t, a) for a in range(1, t - AREAS)) / (t - AREAS - 1)
                    for t in range(AREAS + 2, DOMAINS + 1)) / (AREAS - 1))
            if m in STATIC:
                for t in range(2, DOMAINS + 1):
                    for a in range(1, AREAS + 1):
                        assert w(t, a) == w(1, a), (m, t, a)
        for name, values in per_seed.items():
            mean = sum(values) / len(values)
            assert abs(float(summary[m][name]) - mean) <= 1e-3, (
                m, name, summary[m][name], mean)
    with open(os.path.join(out, "memory.csv")) as f:
        memory = {(r["method"], r["seed"]): r for r in csv.DictReader(f)}
    for (m, seed), r in memory.items():
        if m in ("uniform_replay", "uniform_seq"):
            bioslam = memory[("bioslam", seed)]
            assert int(r["peak_traces"]) <= int(bioslam["peak_traces"]), (r, bioslam)
    with open(os.path.join(out, "curves.png"), "rb") as f:
        assert f.read(4) == b"\x89PNG", "curves.png is not a PNG"
    with open(os.path.join(out, "fleet.csv")) as f:
        fleet = list(csv.DictReader(f))
    for m in ("fleet_shared", "fleet_shared_pairs", "fleet_shared_flat"):
        assert len([r for r in fleet if r["method"] == m]) >= 2, (
            "fleet.csv should have 2 robot rows a seed", m)
    with open(os.path.join(out, "warm_start.csv")) as f:
        warm = list(csv.DictReader(f))
    assert warm, "warm_start.csv should have a row per shared method and seed"
    for r in warm:
        for k in ("hog", "warm_start", "warm_first_segment", "cold_first_segment",
                  "alone_first_segment"):
            assert 0 <= float(r[k]) <= 1, (r, k)
    for m in ["chance"] + METHODS:
        print(f"{m:20s} WR final {summary[m]['wr_final']}, AE {summary[m]['ae']}, "
              f"RA {summary[m]['ra']}")
    print("lifelong: outputs present, numbers agree with their definitions")


def held_out(q, n):
    """Protocol v2's split: the 4th, 8th, ... place of each area."""
    area = q * AREAS // n
    first = next(i for i in range(n) if i * AREAS // n == area)
    return (q - first) % 4 == 3


if __name__ == "__main__":
    main()
