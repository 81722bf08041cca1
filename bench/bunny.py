"""The EKFPnP paper's synthetic experiment (docs/method.md §1): the Stanford bunny, 55 poses.

Protocol, as docs/method.md §9.4 states it:
- the 453 vertices of bun_zipper_res4.ply, centred and scaled to span ~1 unit (call it m);
- a virtual camera 640x480, f = 800 px, principal point at the image centre;
- 55 poses on a path where all six DoF change between consecutive poses and the distance to
  the object first shrinks (4.5 -> 2.4 m) then grows back; every point is checked to
  project inside the image in every frame;
- the EKF starts from the ground truth of frames 0 and 1 (pose of frame 1, velocities from
  the difference) and tracks frames 2..54 with the exact map (synth_points.run_ekf);
  EPnP (+ LM refinement, the paper's EPnP+GN) solves every frame from scratch;
- Gaussian pixel noise sigma = 3 px, 10 runs averaged; errors per pose:
  translation = |c_est - c_gt| / (total path length) [%] with c the camera centre,
  rotation = || (roll, pitch, yaw)_est - (roll, pitch, yaw)_gt || [deg];
- noise sweep sigma = 0..5 px, 10 runs each, mean error over all poses;
- NEES of the EKF's 6x6 pose covariance (6 dof: ideal mean 6).

    python -m bench.bunny [--quick] [--out DIR]
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ekf_vo.core.pnp import solve_epnp
from ekf_vo.tools.synth_points import Sequence, look_at, pose_error, project, run_ekf
from .common import pyplot, section_main, shared_data

N_POSES = 55
WIDTH, HEIGHT, FOCAL_PX = 640, 480, 800.0
RATE_HZ = 10.0
#: process noise of the filter: about the path's peak accelerations (0.85 m/s^2, 0.18 rad/s^2)
ACCEL_SIGMA = 1.0          # m/s^2
ANGULAR_ACCEL_SIGMA = 0.3  # rad/s^2
SIGMA_PX = 3.0
SWEEP_SIGMAS = (0.0, 0.5, 1.0, 2.0, 3.0, 4.0, 5.0)
#: the filter needs a positive R; with noise-free data it uses this floor
MIN_FILTER_SIGMA_PX = 0.1
#: the paper's finding, qualitative (docs/method.md §1)
PAPER = {'epnp_above_ekf_everywhere': True, 'epnp_worst_at_ends': True,
         'ekf_translation_peak_mid_sequence': True, 'epnp_zero_at_zero_noise': True}


class PlyError(ValueError):
    """The PLY file is not the ASCII vertex list we expect."""


def read_ply_vertices(path: Path) -> np.ndarray:
    """(N,3) x y z of an ASCII PLY: header up to `end_header`, then one vertex per line.

    Only the first three properties of `element vertex` are read (x y z in the Stanford
    scans); faces and other elements that follow the vertices are ignored."""
    with open(path, encoding='ascii') as f:
        if f.readline().strip() != 'ply':
            raise PlyError(f'{path}: not a PLY file')
        n_vertex, props, in_vertex = None, [], False
        for line in f:
            words = line.split()
            if not words:
                continue
            if words[0] == 'format' and words[1] != 'ascii':
                raise PlyError(f'{path}: only ASCII PLY is supported, got {words[1]}')
            if words[0] == 'element':
                in_vertex = words[1] == 'vertex'
                if in_vertex:
                    n_vertex = int(words[2])
            elif words[0] == 'property' and in_vertex:
                props.append(words[-1])
            elif words[0] == 'end_header':
                break
        if n_vertex is None or props[:3] != ['x', 'y', 'z']:
            raise PlyError(f'{path}: no vertex element with x y z')
        rows = [f.readline().split()[:3] for _ in range(n_vertex)]
    X = np.array(rows, dtype=float)
    if X.shape != (n_vertex, 3):
        raise PlyError(f'{path}: expected {n_vertex} vertices, read {X.shape}')
    return X


def bunny_points() -> np.ndarray:
    """The 453 bunny vertices centred on their bounding box and scaled to a 1 m extent,
    z up (the scan has y up)."""
    folder = shared_data('bunny')
    if folder is None:
        raise FileNotFoundError("the bunny scan is not in the developers' data folder")
    X = read_ply_vertices(folder / 'bun_zipper_res4.ply')
    X = X[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])     # scan y-up -> world z-up
    X -= 0.5 * (X.min(axis=0) + X.max(axis=0))
    return X / np.max(X.max(axis=0) - X.min(axis=0))


def bunny_path(n: int = N_POSES) -> np.ndarray:
    """(n,4,4) T_world_cam: azimuth, elevation, distance, gaze point and roll all vary
    smoothly; the distance is 4.5 m at both ends and 2.4 m in the middle, where the camera
    swoops in and out (the largest change of velocity is mid-sequence)."""
    s = np.linspace(0.0, 1.0, n)
    r = 4.5 - 2.1 * np.sin(np.pi * s)
    az = np.radians(-30.0 + 60.0 * s + 4.0 * np.sin(2 * np.pi * s))
    el = np.radians(10.0 + 8.0 * np.sin(np.pi * s + 0.3))
    T = np.empty((n, 4, 4))
    for k in range(n):
        pos = r[k] * np.array([np.cos(el[k]) * np.cos(az[k]), np.cos(el[k]) * np.sin(az[k]),
                               np.sin(el[k])])
        gaze = 0.06 * np.array([np.sin(1.6 * np.pi * s[k]), np.cos(1.4 * np.pi * s[k]),
                                np.sin(1.8 * np.pi * s[k] + 1.0)])
        T[k] = look_at(pos, gaze, roll_rad=np.radians(10.0) * np.sin(1.6 * np.pi * s[k] + 0.3))
    return T


def make_sequence() -> Sequence:
    K = np.array([[FOCAL_PX, 0, WIDTH / 2], [0, FOCAL_PX, HEIGHT / 2], [0, 0, 1.0]])
    T = bunny_path()
    return Sequence(K, bunny_points(), T, np.arange(N_POSES) / RATE_HZ, WIDTH, HEIGHT)


def check_visibility(seq: Sequence, margin_px: float = 10.0) -> dict:
    """Every point in front and inside the image (with a margin) in every frame; also the
    image extent the object covers and the per-step change of each DoF."""
    spans, min_margin = [], np.inf
    for T in seq.T_world_cam:
        px, depth = project(seq.K, T, seq.X_world)
        if np.any(depth <= 0):
            raise AssertionError('a bunny point is behind the camera')
        m = np.min(np.concatenate((px[:, 0], seq.width - px[:, 0], px[:, 1],
                                   seq.height - px[:, 1])))
        min_margin = min(min_margin, float(m))
        spans.append(float(np.max(px[:, 0]) - np.min(px[:, 0])))
    if min_margin < margin_px:
        raise AssertionError(f'a bunny point comes within {min_margin:.1f} px of the border')
    pos = seq.T_world_cam[:, :3, 3]
    rpy = np.array([Rotation.from_matrix(T[:3, :3]).as_euler('ZYX') for T in seq.T_world_cam])
    d_pos = np.abs(np.diff(pos, axis=0))
    d_rpy = np.degrees(np.abs(np.diff(np.unwrap(rpy, axis=0), axis=0)))
    dist = np.linalg.norm(pos, axis=1)
    return {'all_visible': True, 'min_border_margin_px': min_margin,
            'object_width_px_min': min(spans), 'object_width_px_max': max(spans),
            'distance_m': [float(dist[0]), float(dist.min()), float(dist[-1])],
            'min_step_change_pos_m': d_pos.min(axis=0), 'min_step_change_rpy_deg':
            d_rpy.min(axis=0),
            # a smooth DoF changes least at its extremum; it must still change there
            'all_dof_change_every_step': bool(np.all(d_pos > 1e-5) and np.all(d_rpy > 1e-5))}


def path_length(T: np.ndarray) -> float:
    return float(np.sum(np.linalg.norm(np.diff(T[:, :3, 3], axis=0), axis=1)))


def rpy_error_deg(R_est: np.ndarray, R_gt: np.ndarray) -> float:
    """Norm of the (roll, pitch, yaw) difference of two camera orientations (ZYX Euler
    angles of R_world_cam), each wrapped to [-180, 180) degrees."""
    e = Rotation.from_matrix(np.stack((R_est, R_gt))).as_euler('ZYX', degrees=True)
    d = (e[0] - e[1] + 180.0) % 360.0 - 180.0
    return float(np.linalg.norm(d))


def _errors(T_est: np.ndarray, T_gt: np.ndarray, length: float) -> tuple[float, float]:
    return (100.0 * float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3])) / length,
            rpy_error_deg(T_est[:3, :3], T_gt[:3, :3]))


def run_trial(seq: Sequence, sigma_px: float, seed: int) -> dict:
    """One noisy run: EKF and EPnP on the same kind of noise (independent draws), frames
    2..54. Returns per-frame translation [% of path] and rotation [deg] errors and NEES."""
    length = path_length(seq.T_world_cam)
    fs = max(sigma_px, MIN_FILTER_SIGMA_PX)
    ekf = run_ekf(seq, sigma_px, np.random.default_rng([seed, 1]), ACCEL_SIGMA,
                  ANGULAR_ACCEL_SIGMA, filter_sigma_px=fs)
    gt = seq.T_world_cam[2:]
    e_ekf = np.array([_errors(T, G, length) for T, G in zip(ekf['T_est'], gt)])
    rng = np.random.default_rng([seed, 2])
    e_pnp, nees_pnp = [], []
    for G in gt:
        px, _ = project(seq.K, G, seq.X_world)
        z = px + rng.normal(0.0, sigma_px, px.shape)
        # no outliers here: a RANSAC threshold of 4 sigma keeps every point, so this is
        # EPnP on all points + LM refinement (the paper's EPnP+GN)
        r = solve_epnp(z, seq.X_world, seq.K, fs, ransac_px=4.0 * fs + 1.0)
        if not r.ok:
            e_pnp.append((np.nan, np.nan))
            nees_pnp.append(np.nan)
            continue
        e_pnp.append(_errors(r.T_world_cam, G, length))
        e = pose_error(r.T_world_cam, G)
        nees_pnp.append(float(e @ np.linalg.solve(r.pose_cov, e)))
    e_pnp = np.array(e_pnp)
    return {'ekf_trans': e_ekf[:, 0], 'ekf_rot': e_ekf[:, 1], 'epnp_trans': e_pnp[:, 0],
            'epnp_rot': e_pnp[:, 1], 'ekf_nees': ekf['nees'], 'epnp_nees': np.array(nees_pnp)}


def anees_bounds(n_runs: int, dof: int = 6, p: float = 0.95) -> tuple[float, float]:
    """Two-sided probability-p bounds of the NEES averaged over n_runs independent runs
    (Bar-Shalom, Li, Kirubarajan 2001, sec. 5.4): chi2(dof*n)/n."""
    a = (1.0 - p) / 2.0
    return (float(chi2.ppf(a, dof * n_runs) / n_runs),
            float(chi2.ppf(1.0 - a, dof * n_runs) / n_runs))


def run(quick: bool = False, out: Path | None = None) -> dict:
    if shared_data('bunny') is None:
        return {'skipped': "the Stanford bunny scan (bun_zipper_res4.ply) is not in the "
                           "developers' data folder"}
    seq = make_sequence()
    vis = check_visibility(seq)
    n_runs = 3 if quick else 10
    length = path_length(seq.T_world_cam)
    trials = [run_trial(seq, SIGMA_PX, seed) for seed in range(n_runs)]
    mean = {k: np.nanmean([t[k] for t in trials], axis=0) for k in trials[0]}
    nees_runs = np.array([t['ekf_nees'] for t in trials])       # (runs, frames)
    lo, hi = anees_bounds(n_runs)
    anees = nees_runs.mean(axis=0)
    frames = np.arange(2, N_POSES)

    sweep = {'sigma_px': list(SWEEP_SIGMAS), 'ekf_trans': [], 'ekf_rot': [],
             'epnp_trans': [], 'epnp_rot': [], 'ekf_nees': []}
    sweep_runs = 3 if quick else 10
    for s in SWEEP_SIGMAS:
        ts = trials if s == SIGMA_PX and sweep_runs == n_runs else \
            [run_trial(seq, s, 100 + seed) for seed in range(sweep_runs)]
        for k in ('ekf_trans', 'ekf_rot', 'epnp_trans', 'epnp_rot', 'ekf_nees'):
            sweep[k].append(float(np.nanmean([t[k] for t in ts])))

    et, pt = mean['ekf_trans'], mean['epnp_trans']
    er, pr = mean['ekf_rot'], mean['epnp_rot']
    third = len(frames) // 3
    checks = {
        'epnp_above_ekf_everywhere_trans': bool(np.all(pt > et)),
        'epnp_above_ekf_everywhere_rot': bool(np.all(pr > er)),
        'frac_poses_epnp_above_ekf_trans': float(np.mean(pt > et)),
        'frac_poses_epnp_above_ekf_rot': float(np.mean(pr > er)),
        # EPnP worst at the ends: mean error of the outer thirds above the middle third's
        'epnp_worst_at_ends': bool(min(pt[:third].mean(), pt[-third:].mean())
                                   > pt[third:-third].mean()),
        'ekf_trans_peak_frame': int(frames[int(np.argmax(et))]),
        'ekf_trans_peak_mid_sequence': bool(third <= int(np.argmax(et)) < len(frames) - third),
        'epnp_zero_at_zero_noise': bool(sweep['epnp_trans'][0] < 1e-3
                                        and sweep['epnp_rot'][0] < 1e-3),
        'ekf_below_epnp_at_all_noise_levels_above_0': bool(all(
            e < p for e, p, s in zip(sweep['ekf_trans'], sweep['epnp_trans'],
                                     SWEEP_SIGMAS) if s > 0)),
    }
    # where the GT path accelerates most (the constant-velocity model's weak spot)
    pos = seq.T_world_cam[:, :3, 3]
    acc = np.linalg.norm(np.diff(pos, 2, axis=0), axis=1) * RATE_HZ ** 2
    res = {
        'setup': {'points': len(seq.X_world), 'poses': N_POSES, 'image': f'{WIDTH}x{HEIGHT}',
                  'f_px': FOCAL_PX, 'rate_hz': RATE_HZ, 'path_length_m': length,
                  'sigma_px': SIGMA_PX, 'runs': n_runs, 'accel_sigma': ACCEL_SIGMA,
                  'angular_accel_sigma': ANGULAR_ACCEL_SIGMA,
                  'gt_peak_accel_m_s2': float(acc.max()),
                  'gt_peak_accel_frame': int(np.argmax(acc) + 1), **vis},
        'frames': frames,
        'per_pose': {k: mean[k] for k in ('ekf_trans', 'ekf_rot', 'epnp_trans', 'epnp_rot')},
        'mean': {'ekf_trans_pct': float(np.mean(et)), 'ekf_rot_deg': float(np.mean(er)),
                 'epnp_trans_pct': float(np.nanmean(pt)),
                 'epnp_rot_deg': float(np.nanmean(pr))},
        'ratio_ekf_over_epnp': {'trans': float(np.mean(et) / np.nanmean(pt)),
                                'rot': float(np.mean(er) / np.nanmean(pr))},
        'nees': {'ekf_mean': float(nees_runs.mean()), 'ekf_median': float(
            np.median(nees_runs)), 'dof': 6, 'anees_95_bounds': [lo, hi],
            'frac_frames_anees_in_bounds': float(np.mean((anees > lo) & (anees < hi))),
            'epnp_mean': float(np.nanmean([t['epnp_nees'] for t in trials]))},
        'sweep': sweep, 'sweep_runs': sweep_runs, 'checks': checks,
    }
    if out is not None:
        res['plots'] = plot(res, out)
    return res


def plot(res: dict, out: Path) -> list[str]:
    plt = pyplot(out)
    f = np.asarray(res['frames'])
    pp = res['per_pose']
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].plot(f, pp['epnp_trans'], 'r.-', label='EPnP+LM (per frame)')
    ax[0].plot(f, pp['ekf_trans'], 'b.-', label='EKF (ours)')
    ax[0].set(xlabel='pose', ylabel='translation error [% of path]',
              title=f'Bunny, sigma = {res["setup"]["sigma_px"]:g} px, '
                    f'{res["setup"]["runs"]} runs')
    ax[1].plot(f, pp['epnp_rot'], 'r.-', label='EPnP+LM (per frame)')
    ax[1].plot(f, pp['ekf_rot'], 'b.-', label='EKF (ours)')
    ax[1].set(xlabel='pose', ylabel='rotation error [deg] (|d roll,pitch,yaw|)',
              title='rotation error per pose')
    for a in ax:
        a.grid(alpha=0.3)
        a.legend()
    fig.tight_layout()
    p1 = out / 'bunny_per_pose.png'
    fig.savefig(p1, dpi=100)
    plt.close(fig)

    sw = res['sweep']
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    ax[0].plot(sw['sigma_px'], sw['epnp_trans'], 'ro-', label='EPnP+LM')
    ax[0].plot(sw['sigma_px'], sw['ekf_trans'], 'bo-', label='EKF (ours)')
    ax[0].set(xlabel='pixel noise sigma [px]', ylabel='mean translation error [% of path]',
              title=f'Noise sweep, {res["sweep_runs"]} runs per level')
    ax[1].plot(sw['sigma_px'], sw['epnp_rot'], 'ro-', label='EPnP+LM')
    ax[1].plot(sw['sigma_px'], sw['ekf_rot'], 'bo-', label='EKF (ours)')
    ax[1].set(xlabel='pixel noise sigma [px]', ylabel='mean rotation error [deg]',
              title='mean over poses 2..54')
    for a in ax:
        a.grid(alpha=0.3)
        a.legend()
    fig.tight_layout()
    p2 = out / 'bunny_noise_sweep.png'
    fig.savefig(p2, dpi=100)
    plt.close(fig)
    return [p1.name, p2.name]


def main(argv: list[str] | None = None) -> int:
    return section_main(argv, __doc__, run, 'bunny', lambda res: print(
        res if 'skipped' in res else
        {k: res[k] for k in ('mean', 'ratio_ekf_over_epnp', 'nees', 'checks')}))


if __name__ == '__main__':
    sys.exit(main())
