#!/usr/bin/env python3
"""fleetmem-eval slam on the real ACES log.

Full run (ctest fleetmem_slam_aces_test, slow tier): the optimised
trajectory's relations error must be well below raw odometry's (at most
half, in mean translation and rotation), loops must be both accepted and
rejected, and the maps and trajectories must be written.

Smoke run (--smoke, ctest fleetmem_slam_smoke_test, `make test`): the first
SMOKE_SCANS scans only; every variant's row of summary.csv (relations
scored, mean translation and rotation error) must equal the relations metric
computed here, in numpy, from the trajectory the variant wrote
(reference_metrics.relations_errors), and the files must be written. It
proves the code path and the report's numbers, not the SLAM's quality.

usage: check_slam_eval.py BIN_DIR DATA_DIR OUT_DIR [--smoke]
"""
import csv
import os
import subprocess
import sys

import numpy as np

import reference_metrics

SMOKE_SCANS = 6000
VARIANTS = ['odometry', 'scan_matching', 'own_memory_loops']


def main():
    bin_dir, data, out = sys.argv[1:4]
    smoke = '--smoke' in sys.argv[4:]
    laser = os.path.join(data, 'laser')
    relations = os.path.join(laser, 'aces.relations')
    command = [os.path.join(bin_dir, 'fleetmem-eval'), 'slam',
               '--log', os.path.join(laser, 'aces.clf.bz2'),
               '--relations', relations, '--out', out]
    if smoke:
        command += ['--scans', str(SMOKE_SCANS)]
    subprocess.check_call(command)
    rows = {r['variant']: r for r in csv.DictReader(open(os.path.join(out, 'summary.csv')))}
    failures = []
    for name in [f'{v}.{ext}' for v in VARIANTS for ext in ('tum', 'png')]:
        path = os.path.join(out, name)
        if not os.path.exists(path) or os.path.getsize(path) == 0:
            failures.append(f'{name} is missing or empty')
    if smoke:
        failures += check_rows(out, rows, relations)
    else:
        odo, loops = rows['odometry'], rows['own_memory_loops']
        for field in ['trans_mean_m', 'rot_mean_deg']:
            if not float(loops[field]) <= 0.5 * float(odo[field]):
                failures.append(f'{field}: SLAM {loops[field]} vs odometry {odo[field]}')
        if int(loops['loops_accepted']) < 10 or int(loops['loops_rejected_geometry']) < 1:
            failures.append(f'loops accepted {loops["loops_accepted"]}, rejected '
                            f'{loops["loops_rejected_geometry"]}')
    for f in failures:
        print('FAIL', f)
    print('slam eval: OK' if not failures else f'slam eval: {len(failures)} failures')
    return 1 if failures else 0


def check_rows(out, rows, relations):
    """Each variant's reported relations error against numpy's on the
    trajectory it wrote (summary.csv prints 4 decimals)."""
    failures = []
    if set(rows) != set(VARIANTS):
        return [f'summary.csv variants {sorted(rows)}']
    for variant in VARIANTS:
        poses = reference_metrics.load_tum_2d(os.path.join(out, variant + '.tum'))
        errors_t, errors_r = reference_metrics.relations_errors(poses, relations)
        row = rows[variant]
        if not errors_t:
            failures.append(f'{variant}: no relation falls within the first scans')
            continue
        print(f'{variant}: {len(errors_t)} relations, translation '
              f'{np.mean(errors_t):.4f} m (report {row["trans_mean_m"]}), rotation '
              f'{np.mean(errors_r):.4f} deg (report {row["rot_mean_deg"]})')
        if int(row['relations']) != len(errors_t):
            failures.append(f'{variant}: {row["relations"]} relations reported, '
                            f'{len(errors_t)} computed')
        for field, want in [('trans_mean_m', np.mean(errors_t)),
                            ('trans_std_m', np.std(errors_t)),
                            ('rot_mean_deg', np.mean(errors_r)),
                            ('rot_std_deg', np.std(errors_r))]:
            if abs(float(row[field]) - want) > 2e-4 + 1e-4 * abs(want):
                failures.append(f'{variant} {field}: report {row[field]}, numpy {want:.6f}')
    return failures


if __name__ == '__main__':
    sys.exit(main())
