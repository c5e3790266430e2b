#!/usr/bin/env python3
"""ctest fleetmem_trajectory_eval_test: fleetmem-eval trajectory against the
independent numpy computation (reference_metrics.py) on the real estimates
in ../shared/data/trajectories: KITTI 00 (ORB-SLAM, S-PTAM) and TUM fr1/xyz
(RGBD-SLAM), SE(3) and Sim(3), RPE by frame and by 100 m (KITTI) / 0.5 m
(TUM). Every figure must agree to 1e-6 (relative) or 1e-9 (absolute).

usage: check_trajectory_eval.py BIN_DIR DATA_DIR
"""
import json
import os
import subprocess
import sys

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
    print('all agree' if failures == 0 else f'{failures} mismatches')
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
