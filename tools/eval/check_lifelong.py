#!/usr/bin/env python3
"""`fleetmem-eval lifelong` end to end on the real data: every method runs
(the memory methods through real fleetmem-server children) and writes the
files the protocol promises, with numbers that agree with their definitions
as computed here (docs/results.md):

  - every curves.csv row: WR = 0.5 r1 + 0.1 (r2 + ... + r6) (BioSLAM's
    weighted recall), recall@k non-decreasing in k, each recall a multiple
    of 1 / (queries per domain);
  - summary.csv from curves.csv: WR final = the mean WR over the six domains
    after the last one, AE = the mean over t of WR of domain t after
    learning it, RA = the mean over t >= 2 of the mean WR of the domains
    before t;
  - the methods that do not learn (classical, gpl_pretrained) score the
    same after every domain.

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

SMOKE_PLACES = 48  # 3 areas of 16 places, every 4th a query: 4 per domain
METHODS = ["classical", "gpl_pretrained", "finetune", "uniform_replay", "bioslam",
           "no_rex", "no_rin", "no_clustering", "no_decay", "bioslam_decoded",
           "fleet_shared"]
STATIC = ["classical", "gpl_pretrained"]
DOMAINS = 6
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
                    "--pretrain-steps", "3",
                    "--steps-per-segment", "2"]
    subprocess.run(command, check=True)

    with open(os.path.join(out, "summary.csv")) as f:
        summary = {r["method"]: r for r in csv.DictReader(f)}
    assert list(summary) == METHODS, list(summary)
    for m, r in summary.items():
        for k in ("wr_final", "ae", "ra"):
            assert 0 <= float(r[k]) <= 1, (m, k, r[k])
    with open(os.path.join(out, "curves.csv")) as f:
        rows = list(csv.DictReader(f))
    wr = {}  # (method, after, domain) -> WR
    for r in rows:
        recall = [float(r[f"r{k}"]) for k in range(1, 7)]
        assert all(a <= b + 1e-9 for a, b in zip(recall, recall[1:])), r
        assert close(float(r["wr"]), 0.5 * recall[0] + 0.1 * sum(recall[1:])), r
        if smoke:
            for x in recall:  # 4 queries per domain
                assert close(x * 4, round(x * 4)), r
        wr[(r["method"], int(r["after_domain"]), int(r["domain"]))] = float(r["wr"])
    for m in METHODS[:-1]:  # fleet_shared reports per robot (fleet.csv)
        cells = [k for k in wr if k[0] == m]
        assert len(cells) == DOMAINS * DOMAINS, (m, len(cells))
        w = lambda t, d: wr[(m, t, d)]
        wr_final = sum(w(DOMAINS, d) for d in range(1, DOMAINS + 1)) / DOMAINS
        ae = sum(w(t, t) for t in range(1, DOMAINS + 1)) / DOMAINS
        ra = sum(sum(w(t, d) for d in range(1, t)) / (t - 1)
                 for t in range(2, DOMAINS + 1)) / (DOMAINS - 1)
        for name, value in (("wr_final", wr_final), ("ae", ae), ("ra", ra)):
            assert abs(float(summary[m][name]) - value) <= 1e-3, (
                m, name, summary[m][name], value)
        if m in STATIC:
            for t in range(2, DOMAINS + 1):
                for d in range(1, DOMAINS + 1):
                    assert w(t, d) == w(1, d), (m, t, d)
    with open(os.path.join(out, "curves.png"), "rb") as f:
        assert f.read(4) == b"\x89PNG", "curves.png is not a PNG"
    with open(os.path.join(out, "fleet.csv")) as f:
        assert len(f.readlines()) == 3, "fleet.csv should have 2 robot rows"
    assert os.path.getsize(os.path.join(out, "encoder.pt")) > 0, "no encoder.pt"
    for m in METHODS:
        print(f"{m:16s} WR final {summary[m]['wr_final']}, AE {summary[m]['ae']}, "
              f"RA {summary[m]['ra']}")
    print("lifelong: outputs present, numbers agree with their definitions")


if __name__ == "__main__":
    main()
