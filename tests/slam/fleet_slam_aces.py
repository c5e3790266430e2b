#!/usr/bin/env python3
"""ctest fleetmem_fleet_slam_test, and the command behind docs/slam.md's fleet
table: fleetmem-robot --slam on the real ACES log against a real
fleetmem-server, loop closure through the fleet's memory.

  1. one robot maps the whole log (its own memory, through the fleet);
  2. two robots split the log: robot-1 maps the first half of the
     keyframes, then robot-2 the second half, starting in its own frame; it
     must find robot-1 through the fleet (verified inter-robot loops) and
     the merged map (robot-1's trajectory and robot-2's in robot-1's frame)
     is scored on every relation;
  3. robot-2's half alone, on an empty fleet, for comparison.

Checks: (1) and (2) at most half of raw odometry's mean translational
error and 0.6 of its mean rotational error; robot-2
anchored to robot-1 by at least one inter-robot loop; every relation scored
in (2). Prints a markdown table; writes OUT_DIR/fleet_slam.csv.

usage: fleet_slam_aces.py BIN_DIR DATA_DIR OUT_DIR
"""
import json
import os
import shutil
import subprocess
import sys
import time

KEYFRAMES_FIRST_HALF = 373  # of ACES' 746 keyframes at 0.5 m


class Server:
    """fleetmem-server on a free port, ready once its --ready-file appears
    (the readiness signal tools/process/server.sh waits for too)."""

    def __init__(self, bin_dir, data_dir):
        self.log = open(data_dir + '.log', 'w')
        ready = data_dir + '.ready'
        if os.path.exists(ready):
            os.unlink(ready)
        self.proc = subprocess.Popen(
            [os.path.join(bin_dir, 'fleetmem-server'), '--listen',
             '127.0.0.1:0', '--data-dir', data_dir, '--ready-file', ready],
            stdout=self.log, stderr=subprocess.STDOUT)
        deadline = time.time() + 60
        while time.time() < deadline:
            if os.path.exists(ready):  # renamed into place: complete
                lines = dict(l.split('=', 1) for l in open(ready).read().split())
                self.port = int(lines['grpc'].rsplit(':', 1)[1])
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        self.proc.kill()
        raise RuntimeError(f'fleetmem-server was not ready; its log: {data_dir}.log')

    def stop(self):
        self.proc.terminate()
        self.proc.wait(timeout=30)
        self.log.close()


def robot(bin_dir, server, data, robot_id, out, extra):
    args = [os.path.join(bin_dir, 'fleetmem-robot'), '--server',
            f'127.0.0.1:{server.port}', '--fleet', 'aces', '--robot-id',
            robot_id, '--source',
            'carmen:' + os.path.join(data, 'laser', 'aces.clf.bz2'),
            '--data-dir', out, '--slam'] + extra
    start = time.time()
    result = subprocess.run(args, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f'{robot_id} exited {result.returncode}:\n{result.stderr[-3000:]}')
    print(result.stderr.strip().splitlines()[-1], flush=True)
    slam = json.load(open(os.path.join(out, 'slam.json')))
    slam['seconds'] = time.time() - start
    return slam


def relations(bin_dir, data, estimate):
    out = subprocess.check_output(
        [os.path.join(bin_dir, 'fleetmem-eval'), 'relations', '--estimate',
         estimate, '--relations', os.path.join(data, 'laser', 'aces.relations'),
         '--json'])
    return json.loads(out)


def merge(out_path, *files):
    rows = []
    for f in files:
        rows += [l for l in open(f) if l.strip()]
    rows.sort(key=lambda l: float(l.split()[0]))
    with open(out_path, 'w') as f:
        f.writelines(rows)


def main():
    bin_dir, data, out = sys.argv[1:4]
    shutil.rmtree(out, ignore_errors=True)
    os.makedirs(out)
    rows = []  # (run, relations report, slam stats)

    server = Server(bin_dir, os.path.join(out, 'server-single'))
    try:
        single = robot(bin_dir, server, data, 'robot-1', os.path.join(out, 'single'), [])
    finally:
        server.stop()
    rows.append(('raw odometry (one robot, whole log)',
                 relations(bin_dir, data, os.path.join(out, 'single', 'odometry.tum')), None))
    rows.append(('SLAM, one robot, own memory through the fleet',
                 relations(bin_dir, data, os.path.join(out, 'single', 'trajectory.tum')), single))

    server = Server(bin_dir, os.path.join(out, 'server-pair'))
    try:
        r1 = robot(bin_dir, server, data, 'robot-1', os.path.join(out, 'r1'),
                   ['--last', str(KEYFRAMES_FIRST_HALF)])
        r2 = robot(bin_dir, server, data, 'robot-2', os.path.join(out, 'r2'),
                   ['--first', str(KEYFRAMES_FIRST_HALF)])
    finally:
        server.stop()
    merged_path = os.path.join(out, 'merged.tum')
    in_r1 = os.path.join(out, 'r2', 'trajectory_in_robot-1.tum')
    anchored = os.path.exists(in_r1)
    if anchored:
        merge(merged_path, os.path.join(out, 'r1', 'trajectory.tum'), in_r1)
        rows.append(('SLAM, two robots through the fleet: merged map',
                     relations(bin_dir, data, merged_path), r2))
    rows.append(('robot-2 (second half) with robot-1 in the fleet',
                 relations(bin_dir, data, os.path.join(out, 'r2', 'trajectory.tum')), r2))

    server = Server(bin_dir, os.path.join(out, 'server-alone'))
    try:
        alone = robot(bin_dir, server, data, 'robot-2', os.path.join(out, 'r2-alone'),
                      ['--first', str(KEYFRAMES_FIRST_HALF)])
    finally:
        server.stop()
    rows.append(('robot-2 (second half) alone on an empty fleet',
                 relations(bin_dir, data, os.path.join(out, 'r2-alone', 'trajectory.tum')), alone))

    print('| run | relations scored | translation (m) | rotation (deg) | loops proposed | '
          'accepted | inter-robot | rejected (geometry) | rejected (graph) | ms / keyframe |')
    print('|---|---|---|---|---|---|---|---|---|---|')
    with open(os.path.join(out, 'fleet_slam.csv'), 'w') as csv:
        csv.write('run,relations,trans_mean_m,trans_std_m,rot_mean_deg,rot_std_deg,'
                  'loops_proposed,loops_accepted,inter_robot_loops,'
                  'rejected_geometry,rejected_graph,ms_per_keyframe\n')
        for name, rel, s in rows:
            t, r = rel['translation_m'], rel['rotation_deg']
            s = s or {}
            ms = s.get('slam_ms_per_keyframe', 0) + s.get('query_ms_per_keyframe', 0)
            cells = [rel['relations_scored'], f"{t['mean']:.3f} ± {t['std']:.3f}",
                     f"{r['mean']:.2f} ± {r['std']:.2f}"] + [
                int(s.get(k, 0)) for k in ['loops_proposed', 'loops_accepted',
                                          'inter_robot_loops', 'loops_rejected_geometry',
                                          'loops_rejected_graph']] + [f'{ms:.1f}']
            print('| ' + name + ' | ' + ' | '.join(str(c) for c in cells) + ' |')
            csv.write(','.join([name, str(rel['relations_scored']), str(t['mean']), str(t['std']),
                                str(r['mean']), str(r['std'])] +
                               [str(int(s.get(k, 0))) for k in
                                ['loops_proposed', 'loops_accepted', 'inter_robot_loops',
                                 'loops_rejected_geometry', 'loops_rejected_graph']] +
                               [f'{ms:.2f}']) + '\n')
    if anchored:
        a = r2['anchors']['robot-1']
        print(f"robot-2's frame in robot-1's: x {a['x']:.3f} m, y {a['y']:.3f} m, "
              f"yaw {a['yaw']:.4f} rad")

    failures = []
    odo = rows[0][1]
    for name, rel, _ in rows[1:3]:
        for key, share in [('translation_m', 0.5), ('rotation_deg', 0.6)]:
            if not rel[key]['mean'] <= share * odo[key]['mean']:
                failures.append(f'{name}: {key} mean {rel[key]["mean"]:.4f} is not at most '
                                f'{share} of odometry\'s {odo[key]["mean"]:.4f}')
    if not anchored or r2.get('inter_robot_loops', 0) < 1:
        failures.append('robot-2 found no verified loop with robot-1 through the fleet')
    elif int(rows[2][1]['relations_scored']) != 1279:
        failures.append(f'merged map scored {rows[2][1]["relations_scored"]} of 1279 relations')
    for f in failures:
        print('FAIL', f)
    return 1 if failures else 0


if __name__ == '__main__':
    sys.exit(main())
