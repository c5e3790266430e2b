#!/usr/bin/env python3
"""An independent numpy computation of the trajectory metrics that
fleetmem-eval trajectory reports, written from the definitions (Umeyama 1991;
Sturm et al. 2012; the KITTI odometry devkit) without sharing code with it.
Prints one JSON object with the same field names as the --json report.

usage: reference_metrics.py REFERENCE ESTIMATE ALIGN(se3|sim3) RPE_DELTA_M
       (RPE_DELTA_M 0: pairs of consecutive frames)
"""
import json
import math
import sys

import numpy as np


def relations_errors(poses, relations_path):
    """The Freiburg relations metric (Kuemmerle et al. 2009) of a 2-D
    estimate: poses is a list of (t, x, y, theta); every relation whose two
    stamps have a pose within 1 ms is scored. Returns the translation
    errors (m) and rotation errors (deg), one per scored relation."""
    times = np.array([p[0] for p in poses])
    errors_t, errors_r = [], []
    for line in open(relations_path):
        v = line.split()
        if len(v) != 8:
            continue
        t1, t2, rx, ry, ryaw = float(v[0]), float(v[1]), float(v[2]), float(v[3]), float(v[7])
        i, j = int(np.argmin(abs(times - t1))), int(np.argmin(abs(times - t2)))
        if abs(times[i] - t1) > 1e-3 or abs(times[j] - t2) > 1e-3:
            continue
        _, xa, ya, ta = poses[i]
        _, xb, yb, tb = poses[j]
        # The estimate's relative pose, then its difference from the relation.
        dx, dy = xb - xa, yb - ya
        ex = math.cos(ta) * dx + math.sin(ta) * dy
        ey = -math.sin(ta) * dx + math.cos(ta) * dy
        ddx, ddy = ex - rx, ey - ry
        errors_t.append(math.hypot(math.cos(ryaw) * ddx + math.sin(ryaw) * ddy,
                                   -math.sin(ryaw) * ddx + math.cos(ryaw) * ddy))
        d = (tb - ta) - ryaw
        errors_r.append(abs(math.degrees(math.atan2(math.sin(d), math.cos(d)))))
    return errors_t, errors_r


def load_tum_2d(path):
    """(t, x, y, yaw) of every pose of a planar TUM trajectory."""
    out = []
    for line in open(path):
        if not line.strip() or line.startswith('#'):
            continue
        t, x, y, _, qx, qy, qz, qw = map(float, line.split()[:8])
        out.append((t, x, y, 2 * math.atan2(qz, qw)))
    return out


def load(path):
    rows = [l.split() for l in open(path) if l.strip() and not l.startswith('#')]
    a = np.array(rows, dtype=float)
    if a.shape[1] == 12:  # KITTI
        poses = np.tile(np.eye(4), (len(a), 1, 1))
        poses[:, :3, :4] = a.reshape(-1, 3, 4)
        return np.arange(len(a), dtype=float), poses, True
    t = a[:, 0]
    poses = np.tile(np.eye(4), (len(a), 1, 1))
    for i, (x, y, z, qx, qy, qz, qw) in enumerate(a[:, 1:]):
        n = np.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        qx, qy, qz, qw = qx / n, qy / n, qz / n, qw / n
        poses[i, :3, :3] = [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]]
        poses[i, :3, 3] = [x, y, z]
    return t, poses, False


def associate(t_ref, t_est, max_diff=0.01):
    # Match each pose of the shorter trajectory to the nearest time of the
    # longer one.
    swap = len(t_est) > len(t_ref)
    short, long_ = (t_ref, t_est) if swap else (t_est, t_ref)
    i_s, i_l = [], []
    for i, t in enumerate(short):
        j = int(np.argmin(np.abs(long_ - t)))
        if abs(long_[j] - t) <= max_diff:
            i_s.append(i)
            i_l.append(j)
    return (i_s, i_l) if swap else (i_l, i_s)


def umeyama(src, dst, scale):
    mu_s, mu_d = src.mean(1, keepdims=True), dst.mean(1, keepdims=True)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd @ xs.T / src.shape[1]
    u, d, vt = np.linalg.svd(cov)
    s = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[2, 2] = -1
    r = u @ s @ vt
    c = np.trace(np.diag(d) @ s) / (xs ** 2).sum(0).mean() if scale else 1.0
    return r, mu_d - c * r @ mu_s, c


def se3_inv(m):
    out = np.eye(4)
    out[:3, :3] = m[:3, :3].T
    out[:3, 3] = -m[:3, :3].T @ m[:3, 3]
    return out


def stats(e):
    e = np.asarray(e)
    return {'count': int(len(e)), 'rmse': float(np.sqrt((e ** 2).mean())),
            'mean': float(e.mean()), 'median': float(np.median(e)),
            'std': float(e.std()), 'min': float(e.min()), 'max': float(e.max())}


def angle(r):
    # Rotation angle from the axis-angle form (stable near zero).
    s = np.linalg.norm([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2
    return np.degrees(np.arctan2(s, (np.trace(r) - 1) / 2))


def main():
    ref_path, est_path, align, delta_m = sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])
    t_ref, ref, kitti = load(ref_path)
    t_est, est, _ = load(est_path)
    if not kitti:
        i_r, i_e = associate(t_ref, t_est)
        ref, est = ref[i_r], est[i_e]
    p_ref, p_est = ref[:, :3, 3].T, est[:, :3, 3].T
    r, t, c = umeyama(p_est, p_ref, align == 'sim3')
    ate = np.linalg.norm(c * r @ p_est + t - p_ref, axis=0)

    # RPE pairs on the estimate's path.
    if delta_m > 0:
        ids, path = [], 0.0
        for i in range(1, len(est)):
            path += np.linalg.norm(est[i, :3, 3] - est[i - 1, :3, 3])
            if path >= delta_m:
                ids.append(i)
                path = 0.0
    else:
        ids = list(range(len(est)))
    te, re = [], []
    for i, j in zip(ids, ids[1:]):
        # SE(3) inverses [R^T, -R^T t] (the files' rotations are orthonormal
        # only to their printed digits; evo inverts them this way too).
        q = se3_inv(ref[i]) @ ref[j]
        p = se3_inv(est[i]) @ est[j]
        e = se3_inv(q) @ p
        te.append(np.linalg.norm(e[:3, 3]))
        re.append(angle(e[:3, :3]))

    # KITTI: segments of 100..800 m of the reference's path, every 10 frames.
    dist = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(ref[:, :3, 3], axis=0), axis=1))])
    t_errs, r_errs = [], []
    for first in range(0, len(ref), 10):
        for length in range(100, 900, 100):
            beyond = np.nonzero(dist > dist[first] + length)[0]
            beyond = beyond[beyond >= first]
            if len(beyond) == 0:
                continue
            last = beyond[0]
            gt = np.linalg.inv(ref[first]) @ ref[last]
            es = np.linalg.inv(est[first]) @ est[last]
            err = np.linalg.inv(es) @ gt
            cosang = np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1)
            t_errs.append(np.linalg.norm(err[:3, 3]) / length)
            r_errs.append(np.arccos(cosang) / length)
    out = {'poses': int(len(ref)), 'ate_rmse_m': stats(ate)['rmse'], 'ate_m': stats(ate),
           'alignment_scale': float(c), 'rpe_trans_rmse_m': stats(te)['rmse'],
           'rpe_trans_m': stats(te), 'rpe_rot_deg': stats(re),
           'kitti_segments': len(t_errs)}
    if t_errs:
        out['kitti_t_err_percent'] = 100 * float(np.mean(t_errs))
        out['kitti_r_err_deg_per_100m'] = 100 * float(np.degrees(np.mean(r_errs)))
    print(json.dumps(out, indent=1))


if __name__ == '__main__':
    main()
