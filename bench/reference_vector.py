"""Our EKF on the exact inputs of the authors' EKFPnP (the ekfpnp_synthetic_sigma3 test vector).

Same observations, same initialisation (the reference's poses of frames 0 and 1, velocities
from their difference), dt = 1 frame, and the reference's error metrics:
  rot_err_deg   = max_i arccos(R_est[:, i] . R_gt[:, i])
  trans_err_pct = 100 |t_est - t_gt| / |t_gt|     (t of X_cam = R X_world + t)
averaged over frames 1..199. Our filter differs from the reference in what docs/method.md §5 and §9.4 describe:
variances (not standard deviations) on R, full covariance (no zeroed cross terms), Joseph
form, process Jacobians at the prior.

    python -m bench.reference_vector [--sigma-mode per_point|frame|reference] [--json PATH]
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from ekf_vo.core import geometry as geo
from ekf_vo.core.ekf import CameraEKF
from .common import shared_data, write_json

METHODS = ('EKFPnP', 'EPnP_GN', 'EPnP', 'MLPnP', 'CEPPnP', 'OPnP', 'RPnP', 'ASPnP')


def _read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, encoding='utf-8') as f:
        header = f.readline().strip().split(',')
    return header, np.genfromtxt(path, delimiter=',', skip_header=1, dtype=float)


def _rot_err_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    cos = np.clip(np.sum(R_est * R_gt, axis=0), -1.0, 1.0)   # column-wise dot products
    return float(np.degrees(np.max(np.arccos(cos))))


def _trans_err_pct(t_est: np.ndarray, t_gt: np.ndarray) -> float:
    return float(100.0 * np.linalg.norm(t_est - t_gt) / np.linalg.norm(t_gt))


def load(folder: Path) -> dict:
    _, gt = _read_csv(folder / 'gt_poses.csv')
    _, obs = _read_csv(folder / 'obs.csv')
    _, pts = _read_csv(folder / 'points_world.csv')
    K = np.loadtxt(folder / 'K.csv', delimiter=',')
    refs = {}
    for m in METHODS:
        _, est = _read_csv(folder / f'est_{m}.csv')
        refs[m] = est
    return {'gt': gt, 'obs': obs, 'points': pts, 'K': K, 'refs': refs}


def run(folder: Path, sigma_mode: str = 'frame', accel_sigma: float = 0.05,
        angular_accel_sigma: float = 0.05, iterations: int = 1) -> dict:
    """Run the EKF; returns mean errors over frames 1..199 for us and the references."""
    d = load(folder)
    gt, obs, K = d['gt'], d['obs'], d['K']
    X_world_all = d['points'][:, 1:4]
    n_frames = int(gt[:, 0].max()) + 1
    R_gt = gt[:, 1:10].reshape(-1, 3, 3)
    t_gt = gt[:, 10:13]
    ref = d['refs']['EKFPnP']

    def T_world_cam_of(row: np.ndarray) -> np.ndarray:
        R_cw, t_cw = row[2:11].reshape(3, 3), row[11:14]
        return geo.invert_T(geo.make_T(R_cw, t_cw))

    # initialisation of the reference (docs/method.md §3.6): frames 0 and 1
    T0, T1 = T_world_cam_of(ref[0]), T_world_cam_of(ref[1])
    v = T1[:3, 3] - T0[:3, 3]
    w = geo.quat_to_rotvec(geo.matrix_to_quat(T0[:3, :3].T @ T1[:3, :3]))
    ekf = CameraEKF(K)
    ekf.initialise(T1, v, w, pose_sigma=1e-8, velocity_sigma=0.025,
                   angular_velocity_sigma=0.025)
    rot, trans, times = [], [], []
    # frame 1 is the initial state, as in the reference
    for frame in range(1, n_frames):
        if frame >= 2:
            rows = obs[obs[:, 0] == frame]
            ids = rows[:, 1].astype(int)
            z = rows[:, 2:4]
            if sigma_mode == 'per_point':
                sigma = np.maximum(rows[:, 6], 0.05)
            elif sigma_mode == 'frame':
                # one sigma per frame: the RMS of the true per-point noise
                sigma = max(float(np.sqrt(np.mean(rows[:, 6] ** 2))), 0.05)
            else:   # the reference's scalar on the diagonal of R, used as a std
                sigma = max(float(gt[frame, 17]), 0.05)
            t0 = time.perf_counter()
            ekf.predict(1.0, accel_sigma, angular_accel_sigma, 1.0)
            ekf.update(z, X_world_all[ids], sigma, iterations)
            times.append((time.perf_counter() - t0) * 1e3)
        T_cw = geo.invert_T(ekf.T_world_cam)
        rot.append(_rot_err_deg(T_cw[:3, :3], R_gt[frame]))
        trans.append(_trans_err_pct(T_cw[:3, 3], t_gt[frame]))
    out = {'ours': {'rot_err_deg': float(np.mean(rot)), 'trans_err_pct': float(np.mean(trans)),
                    'ms_per_frame': float(np.mean(times)), 'per_frame_rot': rot,
                    'per_frame_trans': trans},
           'settings': {'sigma_mode': sigma_mode, 'accel_sigma': accel_sigma,
                        'angular_accel_sigma': angular_accel_sigma,
                        'iterations': iterations}}
    for m, est in d['refs'].items():
        sel = (est[:, 0] >= 1) & np.isfinite(est[:, 14])
        out[m] = {'rot_err_deg': float(np.mean(est[sel, 14])),
                  'trans_err_pct': float(np.mean(est[sel, 15])),
                  'n_frames': int(np.count_nonzero(sel))}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[0])
    parser.add_argument('--sigma-mode', default='frame',
                        choices=('per_point', 'frame', 'reference'))
    parser.add_argument('--accel-sigma', type=float, default=0.05)
    parser.add_argument('--iterations', type=int, default=1)
    parser.add_argument('--json', type=Path, help='also write the result to this file')
    args = parser.parse_args(argv)
    folder = shared_data('ekfpnp_synthetic_sigma3')
    if folder is None:
        print('../shared/data/ekfpnp_synthetic_sigma3 is absent')
        return 1
    res = run(folder, args.sigma_mode, args.accel_sigma, args.accel_sigma, args.iterations)
    if args.json:
        write_json(args.json, res)
    print(f'{"method":<12} {"rot err deg":>12} {"trans err %":>12}')
    for name in ('ours', *METHODS):
        r = res[name]
        print(f'{name:<12} {r["rot_err_deg"]:12.4f} {r["trans_err_pct"]:12.4f}')
    print(f'ours: {res["ours"]["ms_per_frame"]:.3f} ms per predict+update (100 points)')
    return 0


if __name__ == '__main__':
    sys.exit(main())
