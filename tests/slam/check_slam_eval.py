#!/usr/bin/env python3
"""ctest fleetmem_slam_aces_test: fleetmem-eval slam on the real ACES log.
The optimised trajectory's relations error must be well below raw
odometry's (at most half, in mean translation and rotation), loops must be
both accepted and rejected, and the maps and trajectories must be written.

usage: check_slam_eval.py BIN_DIR DATA_DIR OUT_DIR
"""
import csv
import os
import subprocess
import sys


def main():
    bin_dir, data, out = sys.argv[1:4]
    laser = os.path.join(data, 'laser')
    subprocess.check_call([os.path.join(bin_dir, 'fleetmem-eval'), 'slam',
                           '--log', os.path.join(laser, 'aces.clf.bz2'),
                           '--relations', os.path.join(laser, 'aces.relations'),
                           '--out', out])
    rows = {r['variant']: r for r in csv.DictReader(open(os.path.join(out, 'summary.csv')))}
    odo, loops = rows['odometry'], rows['own_memory_loops']
    failures = []
    for field in ['trans_mean_m', 'rot_mean_deg']:
        if not float(loops[field]) <= 0.5 * float(odo[field]):
            failures.append(f'{field}: SLAM {loops[field]} vs odometry {odo[field]}')
    if int(loops['loops_accepted']) < 10 or int(loops['loops_rejected_geometry']) < 1:
        failures.append(f'loops accepted {loops["loops_accepted"]}, rejected '
                        f'{loops["loops_rejected_geometry"]}')
    for name in ['odometry.tum', 'own_memory_loops.tum', 'own_memory_loops.png']:
        if os.path.getsize(os.path.join(out, name)) == 0:
            failures.append(f'{name} is empty')
    for f in failures:
        print('FAIL', f)
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
