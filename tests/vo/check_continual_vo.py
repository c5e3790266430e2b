#!/usr/bin/python3
"""`fleetmem-eval continual-vo --quick` on the real KITTI clips.

Both runs check that the summary holds every method on every deployment
with finite metrics, that AQ and RQ were computed for every learned method,
and that the trajectories, weights and plots were written.

Quick run (ctest fleetmem_continual_vo_test, slow tier): the issue's two
claims as well: cl_slam's ATE after adapting on the new clip is lower than
the same network's before adaptation (fixed), and cl_slam's retention
RQ_trans is no worse than expert_only's.

Smoke run (--smoke, ctest fleetmem_continual_vo_smoke_test, `make test`):
SMOKE_FRAMES frames per clip and a few steps; every learned deployment's
ATE (SE(3)) in summary.csv must equal the one computed here in numpy
(tests/slam/reference_metrics.py) from the trajectory it wrote and the
clip's ground truth. It proves the code paths and the report's numbers, not
the learning.

usage: check_continual_vo.py BIN_DIR DATA_DIR OUT_DIR [--smoke]
"""
import csv
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile

SMOKE_FRAMES = 24
REFERENCE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                         'slam', 'reference_metrics.py')


def main():
    bin_dir, data_dir, out_dir = sys.argv[1:4]
    smoke = "--smoke" in sys.argv[4:]
    shutil.rmtree(out_dir, ignore_errors=True)
    command = [os.path.join(bin_dir, "fleetmem-eval"), "continual-vo",
               "--data-root", data_dir, "--out", out_dir, "--quick"]
    if smoke:
        command += ["--frames", str(SMOKE_FRAMES), "--threads", "1",
                    "--pretrain-steps", "10",
                    "--update-steps", "1"]
    subprocess.run(command, check=True)
    frames = SMOKE_FRAMES if smoke else 51
    with open(os.path.join(out_dir, "summary.csv")) as f:
        rows = list(csv.DictReader(f))
    methods = {"fixed", "expert_only", "generalizer_only", "cl_slam"}
    sequences = {"pre>clip1>clip2", "pre>clip1>clip2>clip1", "pre>clip1>clip1"}
    seen = {(r["method"], r["sequence"]) for r in rows}
    for m in methods:
        for s in sequences:
            assert (m, s) in seen, f"summary.csv lacks {m} on {s}"
    assert {r["sequence"] for r in rows if r["method"] == "classical"} == {
        "clip1", "clip2"}, "classical baseline rows"
    for r in rows:
        assert int(r["frames"]) == frames, r
        for key in ("ate_se3_m", "ate_sim3_m", "rpe_frame_trans_m",
                    "rpe_10m_trans_m", "t_err_10_40m_pct"):
            assert math.isfinite(float(r[key])) and float(r[key]) >= 0, (key, r)
        # The clips are shorter than KITTI's 100 m segments.
        assert r["kitti_t_err_pct"] == "n/a", r
        assert float(r["ate_sim3_m"]) <= float(r["ate_se3_m"]) + 1e-9, r

    def ate(method, sequence):
        return next(float(r["ate_se3_m"]) for r in rows
                    if r["method"] == method and r["sequence"] == sequence)

    with open(os.path.join(out_dir, "continual.csv")) as f:
        scores = {r["method"]: r for r in csv.DictReader(f)}
    assert set(scores) == methods, scores
    for m, s in scores.items():
        assert int(s["aq_sequences"]) == 1 and int(s["rq_pairs"]) == 1, s
    # Without adaptation and without carried-over weights nothing changes.
    assert abs(float(scores["fixed"]["rq_trans"])) < 1e-9, scores["fixed"]

    for m in methods | {"classical"}:
        png = os.path.join(out_dir, f"plot_{m}.png")
        assert os.path.getsize(png) > 1000, png
    order = os.path.join(out_dir, "clip1_first")
    for name in ("pre_clip1_clip2_cl_slam.kitti", "pre_clip1_clip2_cl_slam.tum",
                 "weights/pretrained.pt", "weights/pre_clip1_clip2_cl_slam.pt"):
        assert os.path.getsize(os.path.join(order, name)) > 0, name

    if smoke:
        check_ate(rows, data_dir, order)
        print("continual-vo smoke: OK")
        return

    before = ate("fixed", "pre>clip1>clip2")
    after = ate("cl_slam", "pre>clip1>clip2")
    print(f"clip2 ATE (SE(3)): before adaptation {before:.3f} m, "
          f"cl_slam {after:.3f} m")
    assert after < before, "adaptation did not lower cl_slam's ATE"
    rq_cl = float(scores["cl_slam"]["rq_trans"])
    rq_ex = float(scores["expert_only"]["rq_trans"])
    print(f"RQ_trans: cl_slam {rq_cl:.5f}, expert_only {rq_ex:.5f}")
    assert rq_cl >= rq_ex, "cl_slam retains less than expert_only"
    print("continual-vo quick: OK")


def check_ate(rows, data_dir, order):
    """Every learned deployment's reported ATE against numpy's on the
    trajectory it wrote (summary.csv prints 4 decimals)."""
    checked = 0
    for r in rows:
        if r["method"] == "classical":
            continue
        clip = r["sequence"].split(">")[-1]
        stem = r["sequence"].replace(">", "_") + "_" + r["method"]
        estimate = os.path.join(order, stem + ".kitti")
        with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as ref:
            with open(os.path.join(data_dir, "kitti", clip, "poses.txt")) as f:
                ref.writelines(f.readlines()[:int(r["frames"])])
        want = json.loads(subprocess.check_output(
            [sys.executable, REFERENCE, ref.name, estimate, "se3", "0"]))
        os.unlink(ref.name)
        got = float(r["ate_se3_m"])
        print(f'{r["method"]:17s} {r["sequence"]:24s} ATE {got:.4f} m, '
              f'numpy {want["ate_rmse_m"]:.6f} m')
        assert abs(got - want["ate_rmse_m"]) <= 2e-4 + 1e-4 * want["ate_rmse_m"], (
            r, want)
        checked += 1
    assert checked == 12, checked


if __name__ == "__main__":
    main()
