#!/usr/bin/env python3
"""ctest fleetmem_trajectory_eval_test: fleetmem-eval trajectory against the
independent numpy computation (reference_metrics.py) on the real estimates
in ../shared/data/trajectories: KITTI 00 (ORB-SLAM, S-PTAM) and TUM fr1/xyz
(RGBD-SLAM), SE(3) and Sim(3), RPE by frame and by 100 m (KITTI) / 0.5 m
(TUM); and fleetmem-eval relations on ACES' raw odometry against the
relations metric computed here from the log. Every figure must agree to
1e-6 (relative) or 1e-9 (absolute).

usage: check_trajectory_eval.py BIN_DIR DATA_DIR
"""
import bz2
import json
import math
import os
import subprocess
import sys
import tempfile

import numpy as np

import reference_metrics

HERE = os.path.dirname(os.path.abspath(__file__))
FIELDS = ['poses', 'ate_rmse_m', 'alignment_scale', 'rpe_trans_rmse_m',
          'kitti_segments', 'kitti_t_err_percent', 'kitti_r_err_deg_per_100m']


def main():
    bin_dir, data = sys.argv[1], os.path.join(sys.argv[2], 'trajectories')
    cases = []
    for est in ['KITTI_00_ORB.txt', 'KITTI_00_SPTAM.txt']:
        for align in ['se3', 'sim3']:
            for delta in [0, 100]:
                cases.append(('KITTI_00_gt.txt', est, align, delta))
    for align in ['se3', 'sim3']:
        for delta in [0, 0.5]:
            cases.append(('freiburg1_xyz-groundtruth.txt',
                          'freiburg1_xyz-rgbdslam.txt', align, delta))
    failures = 0
    for ref, est, align, delta in cases:
        r, e = os.path.join(data, ref), os.path.join(data, est)
        mine = [os.path.join(bin_dir, 'fleetmem-eval'), 'trajectory',
                '--reference', r, '--estimate', e, '--align', align, '--json']
        if delta:
            mine += ['--rpe-delta-m', str(delta)]
        got = json.loads(subprocess.check_output(mine))
        want = json.loads(subprocess.check_output(
            [sys.executable, os.path.join(HERE, 'reference_metrics.py'), r, e,
             align, str(delta)]))
        pairs = [(k, got.get(k, 0), want.get(k, 0)) for k in FIELDS]
        for section in ['ate_m', 'rpe_trans_m', 'rpe_rot_deg']:
            for k in ['count', 'rmse', 'mean', 'median', 'std', 'min', 'max']:
                pairs.append((section + '.' + k, float(got[section][k]),
                              want[section][k]))
        for name, a, b in pairs:
            a, b = float(a), float(b)
            ok = abs(a - b) <= max(1e-9, 1e-6 * abs(b))
            if not ok:
                failures += 1
                print(f'MISMATCH {est} {align} delta={delta} {name}: '
                      f'fleetmem {a!r} numpy {b!r}')
        print(f'{est:32s} {align:4s} rpe-delta {delta!s:>4}: ATE rmse '
              f'{got["ate_rmse_m"]:.6f} m, RPE rmse {got["rpe_trans_rmse_m"]:.6f} m, '
              f't_err {got["kitti_t_err_percent"]:.4f} %, r_err '
              f'{got["kitti_r_err_deg_per_100m"]:.4f} deg/100 m')
    failures += check_relations(bin_dir, os.path.join(sys.argv[2], 'laser'))
    print('all agree' if failures == 0 else f'{failures} mismatches')
    return 1 if failures else 0


def check_relations(bin_dir, laser):
    """The Freiburg relations metric of ACES' raw odometry, computed here
    from the log and the relations file, against fleetmem-eval relations
    on the same poses written as TUM."""
    poses = []  # (t, x, y, theta) of every FLASER record
    for line in bz2.open(os.path.join(laser, 'aces.clf.bz2'), 'rt'):
        f = line.split()
        if not f or f[0] != 'FLASER':
            continue
        n = int(f[1])
        x, y, th = map(float, f[2 + n:5 + n])
        poses.append((float(f[8 + n]), x, y, th))
    errors_t, errors_r = reference_metrics.relations_errors(
        poses, os.path.join(laser, 'aces.relations'))
    with tempfile.NamedTemporaryFile('w', suffix='.tum', delete=False) as tum:
        for t, x, y, th in poses:
            tum.write(f'{t:.6f} {x!r} {y!r} 0 0 0 {math.sin(th / 2)!r} {math.cos(th / 2)!r}\n')
    got = json.loads(subprocess.check_output(
        [os.path.join(bin_dir, 'fleetmem-eval'), 'relations', '--estimate', tum.name,
         '--relations', os.path.join(laser, 'aces.relations'), '--json']))
    os.unlink(tum.name)
    failures = 0
    for name, a, b in [('count', int(got['relations_scored']), len(errors_t)),
                       ('translation mean', got['translation_m']['mean'], np.mean(errors_t)),
                       ('translation std', got['translation_m']['std'], np.std(errors_t)),
                       ('rotation mean', got['rotation_deg']['mean'], np.mean(errors_r)),
                       ('rotation std', got['rotation_deg']['std'], np.std(errors_r))]:
        if abs(float(a) - float(b)) > max(1e-9, 1e-6 * abs(float(b))):
            failures += 1
            print(f'MISMATCH ACES relations {name}: fleetmem {a!r} numpy {b!r}')
    print(f'ACES raw odometry relations: {len(errors_t)} scored, translation '
          f'{np.mean(errors_t):.4f} +- {np.std(errors_t):.4f} m, rotation '
          f'{np.mean(errors_r):.4f} +- {np.std(errors_r):.4f} deg')
    return failures


if __name__ == '__main__':
    sys.exit(main())
